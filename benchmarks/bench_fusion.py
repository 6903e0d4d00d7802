#!/usr/bin/env python3
"""Fusion latency (CPU): time the fusion step adds per query — posterior, votes, 68/95 % radii —
against the paper's re-rank, at top-p 50 and 500. Target (issue 9): <= 2 ms at top-p 50, <= 10 ms
at top-p 500.

The map is synthetic (random unit descriptors at the real MP-16 coordinates of
../shared/data/mp16_coords, random positions if absent), calibrated like a built map; priors are
drawn from the shipped VLM error model around each query's true reference. Retrieval time is
shown for scale; ``fusion`` is the ``rerank_ms`` the localizer reports (everything after the
FAISS search). All numbers come from this one run.

    .venv/bin/python benchmarks/bench_fusion.py [--refs 50000] [--dim 256] [--queries 200]
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

from vlm_vpr_ros.localization.fusion.calibration import _sample_prior  # noqa: E402
from vlm_vpr_ros.localization.fusion.error_model import load_error_models  # noqa: E402
from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig  # noqa: E402
from vlm_vpr_ros.mapping.assemble import assemble_map
from vlm_vpr_ros.mapping.build_images import write_map_calibration  # noqa: E402
from vlm_vpr_ros.maps.reference_map import ReferenceMap  # noqa: E402
from vlm_vpr_ros.priors.provider import Prior, PriorResult  # noqa: E402

SHARED = Path(os.environ.get("VLM_VPR_SHARED", REPO.parent / "shared"))
MP16 = SHARED / "data" / "mp16_coords" / "coordinates_100K.csv"


def coords(n: int, rng: np.random.Generator) -> np.ndarray:
    if MP16.is_file():
        with MP16.open() as fh:
            rows = [(float(r["LAT"]), float(r["LON"])) for r in csv.DictReader(fh)]
        return np.array(rows[:n])
    return np.stack([rng.uniform(-60, 70, n), rng.uniform(-180, 180, n)], 1)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--refs", type=int, default=50_000)
    ap.add_argument("--dim", type=int, default=256)
    ap.add_argument("--queries", type=int, default=200)
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    print(cpuinfo.cpu_line(), flush=True)
    rng = np.random.default_rng(0)
    xy = coords(args.refs, rng)
    n = len(xy)
    desc = rng.normal(size=(n, args.dim)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    ident = {"name": "synthetic", "dim": args.dim, "config": {}, "preprocessing": {}}
    model = load_error_models().get()
    with tempfile.TemporaryDirectory() as tmp:
        m = assemble_map(desc, xy, [f"r{i}" for i in range(n)], ident, {}, "kmeans", 100)
        m.save(Path(tmp) / "map")
        write_map_calibration(m, desc, xy)
        m = ReferenceMap.load(Path(tmp) / "map")
        rows = rng.choice(n, size=args.queries, replace=False)
        queries = desc[rows] + rng.normal(0, 0.03, (len(rows), args.dim)).astype(np.float32)
        priors = [PriorResult(Prior(*_sample_prior(xy[r, 0], xy[r, 1], model, rng), "vlm"),
                              "vlm") for r in rows]
        print(f"fusion latency: {n} references, {args.dim}-D, {len(m.submaps)} submaps, "
              f"{len(rows)} queries with priors from the VLM error model")
        head = (f"{'mode':<12}{'top-p':>6}{'candidates':>12}{'retrieval ms':>14}"
                f"{'fusion ms (median)':>20}{'p95':>8}{'target':>9}")
        print(head)
        print("-" * len(head))
        for p in (50, 500):
            for fusion in ("paper", "posterior"):
                loc = Localizer(m, LocalizerConfig(top_p=p, fusion=fusion))
                loc.localize(queries[0], priors[0])  # warm-up
                fus, ret, cands = [], [], []
                for q, pr in zip(queries, priors):
                    h = loc.localize(q, pr)
                    fus.append(h.timings_ms["rerank_ms"])
                    ret.append(h.timings_ms["retrieval_ms"])
                    cands.append(len(h.candidates))
                target = {50: 2.0, 500: 10.0}[p] if fusion == "posterior" else None
                med = statistics.median(fus)
                p95 = sorted(fus)[int(0.95 * (len(fus) - 1))]
                verdict = "" if target is None else (f"<= {target:g}" + (" ok" if med <= target
                                                                           else " MISS"))
                print(f"{fusion:<12}{p:>6}{statistics.median(cands):>12.0f}"
                      f"{statistics.median(ret):>14.2f}{med:>20.2f}{p95:>8.2f}{verdict:>9}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
