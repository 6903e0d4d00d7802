#!/usr/bin/env python3
"""Fit the shipped VLM prior error model (vlm_vpr_ros/data/vlm_error_model.json) from real answers.

    python scripts/fit_error_model.py --answers ../shared/data/vlm_answers/im2gps/*.csv \
        --ground-truth ../shared/data/im2gps/ground_truth.csv \
        --out vlm_vpr_ros/data/vlm_error_model.json

Answers are parsed with the package's robust parser (the one `vlm-vpr priors score` uses, which
reproduces gpt-4o's published IM2GPS accuracy); unreadable answers are failed priors and are not
part of the distance model. One model per answers file plus a pooled ``default``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vlm_vpr_ros.cli.priors import score_answers  # noqa: E402
from vlm_vpr_ros.evaluation.metrics import read_ground_truth  # noqa: E402
from vlm_vpr_ros.localization.fusion.error_model import (ERROR_MODEL_FORMAT, ERROR_MODEL_VERSION,
                                                         fit_error_model)
from vlm_vpr_ros.geodesy import THRESHOLDS_KM  # noqa: E402
from vlm_vpr_ros.files.atomic import atomic_write_json  # noqa: E402
from vlm_vpr_ros.priors.vlm import read_answers_csv  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--answers", nargs="+", required=True)
    ap.add_argument("--ground-truth", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--min-sigma-km", type=float, default=0.1)
    args = ap.parse_args()
    truth = read_ground_truth(args.ground_truth)
    models, sources, pooled = {}, [], []
    for path in sorted(args.answers):
        p = Path(path)
        summary, rows = score_answers(read_answers_csv(p), truth, "robust")
        errs = [r["error_km"] for r in rows if r["error_km"] is not None]
        pooled += errs
        model, ll = fit_error_model(errs, min_sigma_km=args.min_sigma_km, name=p.stem)
        cdf = model.cdf([t for t in THRESHOLDS_KM])
        n = len(errs)
        emp = [round(100 * sum(e <= t for e in errs) / n, 2) for t in THRESHOLDS_KM]
        models[p.stem] = {**model.as_dict(), "n_readable": n, "n_answers": summary["images"],
                          "mean_loglik": round(ll, 4),
                          "readable_accuracy_pct": dict(zip([f"{t:g}km" for t in THRESHOLDS_KM],
                                                            emp)),
                          "model_cdf_pct": dict(zip([f"{t:g}km" for t in THRESHOLDS_KM],
                                                    [round(100 * float(c), 2) for c in cdf]))}
        sources.append({"file": f"vlm_answers/im2gps/{p.name}",
                        "sha256": hashlib.sha256(p.read_bytes()).hexdigest(),
                        "readable": n, "answers": summary["images"]})
        print(f"{p.stem:<34} n={n:<4} sigmas={[round(s, 1) for s in model.sigmas_km]} "
              f"w={[round(w, 3) for w in model.weights]} u={model.uniform_weight:.3f} "
              f"emp={emp} model={[round(100 * float(c), 1) for c in cdf]}")
    model, ll = fit_error_model(pooled, min_sigma_km=args.min_sigma_km, name="pooled")
    n = len(pooled)
    models["pooled"] = {**model.as_dict(), "n_readable": n, "mean_loglik": round(ll, 4),
                        "readable_accuracy_pct": {f"{t:g}km": round(100 * sum(
                            e <= t for e in pooled) / n, 2) for t in THRESHOLDS_KM},
                        "model_cdf_pct": {f"{t:g}km": round(100 * float(model.cdf(t)), 2)
                                          for t in THRESHOLDS_KM}}
    print(f"{'pooled':<34} n={n:<4} sigmas={[round(s, 1) for s in model.sigmas_km]} "
          f"w={[round(w, 3) for w in model.weights]} u={model.uniform_weight:.3f}")
    doc = {
        "format": ERROR_MODEL_FORMAT, "version": ERROR_MODEL_VERSION, "default": "pooled",
        "provenance": {
            "what": "error of VLM (lat, lon) answers vs ground truth on IM2GPS (237 images); "
                    "mixture of von Mises-Fisher components + uniform, fitted by EM",
            "ground_truth": "im2gps/ground_truth.csv (TIBHannover/GeoEstimation "
                            "meta/im2gps_places365.csv)",
            "answers_source": "OliverGrainge/PRIV-LOC-VLM results/responses/ (raw answers; "
                              "not shipped, only these fitted numbers)",
            "sources": sources, "parser": "robust (vlm_vpr_ros.priors.parsing)",
            "min_sigma_km": args.min_sigma_km,
            "fitted": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "script": "scripts/fit_error_model.py",
        },
        "models": models,
    }
    atomic_write_json(Path(args.out), doc)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
