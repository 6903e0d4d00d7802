"""``vlm-vpr priors score`` (accuracy of recorded VLM answers) and ``vlm-vpr priors ask`` (one
live query against an OpenAI-compatible endpoint)."""

from __future__ import annotations

import argparse
import json
import logging
import os
from pathlib import Path
from typing import Any

from vlm_vpr_ros.cli.common import add_prior_args
from vlm_vpr_ros.files.csvio import write_csv_atomic
from vlm_vpr_ros.config import parse_kv
from vlm_vpr_ros.errors import ConfigError, ImageDecodeError
from vlm_vpr_ros.evaluation.metrics import errors_km, read_ground_truth, summarize
from vlm_vpr_ros.geodesy import THRESHOLDS_KM
from vlm_vpr_ros.priors import PriorQuery, create_prior_provider
from vlm_vpr_ros.priors.parsing import PARSER_MODES, parse_answer
from vlm_vpr_ros.redact import redact, redact_obj

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("priors", help="VLM priors: score recorded answers, ask an endpoint")
    psub = p.add_subparsers(dest="priors_command", metavar="ACTION")
    psub.required = True

    s = psub.add_parser(
        "score", help="accuracy of recorded raw VLM answers against ground truth",
        description="Parse every answer (CSV filename,response) and score it against the ground "
                    "truth over ALL answered images that have ground truth: an answer without "
                    "readable in-range coordinates counts as a miss.")
    s.add_argument("--answers", required=True, action="append", metavar="CSV",
                   help="answers CSV (columns filename, response); repeatable")
    s.add_argument("--ground-truth", required=True, metavar="CSV",
                   help="file, lat, lon or IMG_ID, LAT, LON")
    s.add_argument("--parser", default="robust", choices=[*PARSER_MODES, "all"],
                   help="strict: JSON only; robust (default): JSON, prose, N/S/E/W, DMS; "
                        "paper: the paper's first-two-numbers regex; all: a row per mode")
    s.add_argument("--details", metavar="OUT.csv", default=None,
                   help="write one row per image (answer parsed, error km, reason)")
    s.add_argument("--json", action="store_true",
                   help="print only {images, readable, accuracy, median_km} (one answers CSV, "
                        "one parser)")
    s.set_defaults(func=cmd_score)

    a = psub.add_parser(
        "ask", help="ask the configured VLM endpoint for one image's position",
        description="One request through the prior provider (default 'openai'): least-to-most "
                    "prompt, retries, cache. Exit status 1 when no prior came back.")
    a.add_argument("--image", required=True, metavar="FILE", help="the image to ask about")
    a.add_argument("--base-url", default=None, metavar="URL",
                   help="shortcut for --prior-option base_url=URL (default OpenAI; e.g. "
                        "http://localhost:11434/v1 for Ollama)")
    a.add_argument("--model", default=None, help="shortcut for --prior-option model=NAME")
    a.add_argument("--json", action="store_true", help="print only the result as JSON")
    add_prior_args(a)
    a.set_defaults(func=cmd_ask)


def score_answers(answers: dict[str, str], truth: dict[str, tuple[float, float]],
                  parser: str = "robust") -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """``({"images", "readable", "accuracy", "median_km", "reasons"}, per-image rows)``."""
    by_base = {os.path.basename(k): v for k, v in truth.items()}
    est, gt, rows, reasons = [], [], [], {}
    for name, raw in answers.items():
        g = truth.get(name) or by_base.get(os.path.basename(name))
        if g is None:
            continue
        p = parse_answer(raw, parser)
        est.append((p.lat, p.lon) if p.ok else None)
        gt.append(g)
        if not p.ok:
            reasons[p.reason] = reasons.get(p.reason, 0) + 1
        rows.append({"file": name, "lat": p.lat, "lon": p.lon, "gt_lat": g[0], "gt_lon": g[1],
                     "reason": p.reason, "method": p.method})
    errs = errors_km(est, gt)
    for row, e in zip(rows, errs):
        row["error_km"] = None if e is None else round(e, 3)
    summary = summarize(errs)
    return ({"images": summary["n"], "readable": sum(e is not None for e in est),
             "accuracy": summary["accuracy"], "median_km": summary["median_km"],
             "reasons": dict(sorted(reasons.items()))}, rows)


DETAILS_COLUMNS = ["answers", "parser", "file", "lat", "lon", "gt_lat", "gt_lon", "error_km",
                   "reason", "method"]


def cmd_score(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.priors.vlm import read_answers_csv

    modes = list(PARSER_MODES) if args.parser == "all" else [args.parser]
    if args.json and (len(modes) > 1 or len(args.answers) > 1):
        raise ConfigError("--json prints one object: give one --answers CSV and one --parser")
    if args.details:  # checked before any work: never a user's file
        from vlm_vpr_ros.files.outputs import check_csv_output

        check_csv_output(args.details, DETAILS_COLUMNS, "--details",
                         [args.ground_truth, *args.answers])
    truth = read_ground_truth(args.ground_truth)
    results, details = [], []
    for path in args.answers:
        answers = read_answers_csv(path)
        for mode in modes:
            summary, rows = score_answers(answers, truth, mode)
            if len(rows) < len(answers):
                log.warning("%s: %d answer(s) have no ground truth and are not scored", path,
                            len(answers) - len(rows))
            results.append((f"{Path(path).stem} [{mode}]", summary))
            details += [{"answers": Path(path).stem, "parser": mode, **r} for r in rows]
    if args.details:
        write_csv_atomic(args.details, DETAILS_COLUMNS, details)
    if args.json:
        s = results[0][1]
        print(json.dumps({k: s[k] for k in ("images", "readable", "accuracy", "median_km")}))
        return 0
    keys = [f"{t:g}km" for t in THRESHOLDS_KM]
    head = (f"{'answers [parser]':<44}{'readable':>12}" + "".join(f"{k:>9}" for k in keys)
            + f"{'median km':>11}")
    print(head)
    print("-" * len(head))
    for name, s in results:
        med = "-" if s["median_km"] is None else f"{s['median_km']:.1f}"
        print(f"{name:<44}{s['readable']:>5}/{s['images']:<6}"
              + "".join(f"{s['accuracy'][k]:>8.2f}%" for k in keys) + f"{med:>11}")
    for name, s in results:
        if s["reasons"]:
            why = ", ".join(f"{k}={v}" for k, v in s["reasons"].items())
            print(f"  {name}: unreadable {why}")
    return 0


def cmd_ask(args: argparse.Namespace) -> int:
    options = parse_kv(args.prior_option)
    name = args.prior or ("recorded" if args.priors else "openai")
    if args.priors:
        options.setdefault("path", args.priors)
    if args.base_url:
        options["base_url"] = args.base_url
    if args.model:
        options["model"] = args.model
    try:
        data = Path(args.image).read_bytes()
    except OSError as exc:
        raise ImageDecodeError(f"cannot read image {args.image}: {exc.strerror}") from None
    provider = create_prior_provider(name, options)
    try:
        result = provider.get(PriorQuery(encoded=data, key=os.path.basename(args.image)),
                              timeout_s=args.prior_timeout)
    finally:
        provider.close()
    # everything printed passes the redaction point: an endpoint may echo request headers
    if args.json:
        p = result.prior
        print(redact(json.dumps(redact_obj({
            "ok": result.ok, "lat": p.lat if p else None, "lon": p.lon if p else None,
            "source": result.source, "reason": result.reason,
            "latency_s": round(result.latency_s, 3), "raw_text": result.raw_text,
            "extra": result.extra}))))
    elif result.prior is not None:
        how = ", ".join(x for x in (result.extra.get("parse_method"),
                                    result.extra.get("parse_path"),
                                    "cached" if result.extra.get("cached") else None) if x)
        print(redact(f"{result.prior.lat:.6f} {result.prior.lon:.6f}  ({result.source}, "
                     f"{result.latency_s:.2f} s{', ' + how if how else ''})"))
    else:
        print(redact(f"no prior: {result.reason} ({result.source}, "
                     f"{result.latency_s:.2f} s)"))
        if result.raw_text:
            print(redact(f"answer: {' '.join(result.raw_text[:500].split())}"))
    return 0 if result.ok else 1
