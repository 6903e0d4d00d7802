#!/usr/bin/env python3
"""Retrieval on SF night (../shared/data/sf_night: 332 references, 34 night queries) per global
descriptor: recall within 25 m at rank 1 and in the top 20, no prior, for the queries at full
size and fitted in 640x480; the descriptor's cost per query image and the map's build time.

Each descriptor gets its own map, built as a user builds one (retrieval only, so the build is
short)::

    vlm-vpr build-map --images sf_night --coords sf_night/database.csv --out MAP \\
        --partition kmeans --clusters 8 --descriptor NAME --local-features none

then every query goes through the pipeline without a prior: the descriptor (timed), retrieval
and fusion. ``R@1``: the first candidate within 25 m of the truth; ``R@20``: one of the first
20 (the right place is in the top 20 that verification sees). Counts are of the 34 queries.

Variants are ``NAME`` or ``NAME:KEY=VALUE,...`` (descriptor options, e.g.
``vlad_xfeat:n_words=128``). Without the data it prints "no SF night data; nothing measured"
and exits 0.

    .venv/bin/python benchmarks/bench_retrieval.py [--data DIR]
        [--variants "vlad_rootsift;vlad_xfeat"] [--threads N] [--work DIR]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.geodesy import haversine_km  # noqa: E402
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline  # noqa: E402
from vlm_vpr_ros.localization.verification.conditions import parse_condition  # noqa: E402
from vlm_vpr_ros.mapping.coords_csv import read_coords_csv  # noqa: E402

SHARED = Path(os.environ.get("VLM_VPR_SHARED", REPO.parent / "shared"))
DEFAULT_VARIANTS = "vlad_rootsift;vlad_xfeat"
CONDITIONS = ("full", "fit640x480")
RADIUS_M = 25.0
TOP = 20


def parse_variant(text: str) -> tuple[str, dict[str, str]]:
    name, _, opts = text.strip().partition(":")
    options = {}
    for kv in filter(None, (o.strip() for o in opts.split(","))):
        key, eq, value = kv.partition("=")
        if not eq:
            raise SystemExit(f"variant {text!r}: options are KEY=VALUE, got {kv!r}")
        options[key] = value
    return name, options


def build(data: Path, out: Path, name: str, options: dict[str, str], threads: int | None
          ) -> float:
    """Build the map with the CLI; its wall time in seconds."""
    cmd = [sys.executable, "-m", "vlm_vpr_ros.cli", "-q", "build-map", "--images", str(data),
           "--coords", str(data / "database.csv"), "--out", str(out), "--partition", "kmeans",
           "--clusters", "8", "--descriptor", name, "--local-features", "none"]
    for k, v in options.items():
        cmd += ["--descriptor-option", f"{k}={v}"]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    t0 = time.monotonic()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"build-map {name} failed ({proc.returncode}): {proc.stderr.strip()}")
    return time.monotonic() - t0


def measure(map_dir: Path, queries: list, images: list) -> dict[str, tuple[int, int, float]]:
    """Per condition: (R@1 count, R@20 count, median descriptor ms)."""
    pipe = LocalizationPipeline.open(map_dir, verification={"top_k": 0})
    pipe.describe(images[0])  # warm-up (first-call allocations), not timed
    out = {}
    for cond_name in CONDITIONS:
        cond = parse_condition(cond_name)
        r1 = r20 = 0
        ms = []
        for (_, lat, lon), image in zip(queries, images):
            frame = cond.apply(image)
            t0 = time.perf_counter()
            desc = pipe.describe(frame)
            ms.append((time.perf_counter() - t0) * 1e3)
            hyp = pipe.localize_descriptor(desc, None)
            d_m = [haversine_km(lat, lon, c.lat, c.lon) * 1000 for c in hyp.candidates[:TOP]]
            r1 += bool(d_m) and d_m[0] <= RADIUS_M
            r20 += bool(d_m) and min(d_m) <= RADIUS_M
        out[cond_name] = (r1, r20, statistics.median(ms))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=SHARED / "data" / "sf_night",
                    help="folder with database/, database.csv, queries/, queries.csv")
    ap.add_argument("--variants", default=DEFAULT_VARIANTS,
                    help=f"';'-separated NAME[:KEY=VALUE,...] (default {DEFAULT_VARIANTS})")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch/OpenMP threads (default: the libraries' own)")
    ap.add_argument("--work", type=Path, default=None, help="keep the maps here")
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    data = args.data
    if not all((data / p).exists() for p in ("database.csv", "queries.csv")):
        print("no SF night data; nothing measured")
        return 0
    variants = [parse_variant(v) for v in args.variants.split(";") if v.strip()]
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    print(cpuinfo.cpu_line(), flush=True)
    queries = read_coords_csv(data / "queries.csv")
    images = [load_image(data / f) for f, _, _ in queries]
    n = len(queries)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_retrieval_") as tmp:
        work = args.work or Path(tmp)
        for i, (name, options) in enumerate(variants):
            out = work / f"map_{i}_{name}"
            build_s = build(data, out, name, options, args.threads)
            res = measure(out, queries, images)
            opts = ", ".join(f"{k}={v}" for k, v in options.items()) or "defaults"
            cells = [f"{res[c][0]}/{n}" for c in CONDITIONS] + \
                    [f"{res[c][1]}/{n}" for c in CONDITIONS] + \
                    [f"{res[c][2]:.0f}" for c in CONDITIONS]
            rows.append(f"| {name} | {opts} | " + " | ".join(cells) + f" | {build_s:.0f} |")
            print(f"  {name} ({opts}) done", file=sys.stderr, flush=True)
    threads = args.threads or "library default"
    print(f"# SF night: {n} queries, {RADIUS_M:.0f} m, no prior; maps: kmeans 8 clusters, "
          f"--local-features none; torch threads: {threads}")
    print("| descriptor | options | R@1 full | R@1 640x480 | top-20 full | top-20 640x480 "
          "| descriptor ms full | descriptor ms 640x480 | build s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
