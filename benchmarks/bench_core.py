#!/usr/bin/env python3
"""Core speed benchmark (CPU): descriptor time per 640x480 frame, map build rate, and query time
(retrieve + re-rank) in a ~41k-reference submap vs. a flat global index over 100k references.

Descriptors for the query benchmark are synthetic (random unit vectors, 512-D like the paper's
ResNet-50 models) placed at the 100k real MP-16 coordinates of ../shared/data/mp16_coords (random
positions if that folder is absent). All ratios come from this one run.

    .venv/bin/python benchmarks/bench_core.py [--refs 100000] [--dim 512] [--queries 200]
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from vlm_vpr_ros.evaluation.demo import DEMO_DATA, make_query  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig  # noqa: E402
from vlm_vpr_ros.maps.assemble import assemble_map
from vlm_vpr_ros.maps.build_images import build_map  # noqa: E402
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline  # noqa: E402
from vlm_vpr_ros.priors.base import Prior, PriorResult  # noqa: E402

MP16 = REPO.parent / "shared" / "data" / "mp16_coords" / "coordinates_100K.csv"


def ms(samples: list[float]) -> str:
    s = sorted(samples)
    return f"{statistics.median(s) * 1e3:8.2f} ms (p95 {s[int(0.95 * (len(s) - 1))] * 1e3:.2f})"


def coords(n: int) -> tuple[np.ndarray, str]:
    if MP16.is_file():
        with MP16.open() as fh:
            rows = [(float(r["LAT"]), float(r["LON"])) for r in csv.DictReader(fh)]
        c = np.array(rows[:n])
        if len(c) >= n:
            return c, f"MP-16 ({len(c)} real positions)"
    rng = np.random.default_rng(0)
    return np.stack([rng.uniform(-60, 70, n), rng.uniform(-180, 180, n)], 1), "random positions"


def bench_frames(n_frames: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        build_map(DEMO_DATA / "images", DEMO_DATA / "coords.csv", Path(tmp) / "m",
                  partition="country", progress=False)
        build_s = time.perf_counter() - t0
        pipe = LocalizationPipeline.open(Path(tmp) / "m")
        files = sorted((DEMO_DATA / "images").glob("*.jpg"))[:n_frames]
        frames = [make_query(load_image(f), np.random.default_rng(i))
                  for i, f in enumerate(files)]
        assert frames[0].shape == (480, 640, 3)
        prior = PriorResult(Prior(45.0, 7.0, "bench"), "bench")
        pipe.localize_image(frames[0], prior)  # warm-up
        desc_t, total_t = [], []
        for fr in frames:
            t0 = time.perf_counter()
            pipe.describe(fr)
            t1 = time.perf_counter()
            pipe.localize_image(fr, prior)
            total_t.append(time.perf_counter() - t1)
            desc_t.append(t1 - t0)
    return {"build_img_s": 71 / build_s, "desc": desc_t, "frame": total_t}


def bench_queries(n_refs: int, dim: int, n_queries: int, top_p: int) -> dict:
    c, src = coords(n_refs)
    rng = np.random.default_rng(1)
    desc = rng.normal(size=(len(c), dim)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    ident = {"name": "synthetic", "dim": dim, "config": {}, "preprocessing": {}}
    ids = [f"r{i}" for i in range(len(c))]
    t0 = time.perf_counter()
    country = assemble_map(desc, c, ids, ident, {}, "country")
    part_s = time.perf_counter() - t0
    flat = assemble_map(desc, c, ids, ident, {}, "none")
    big = max(country.submaps, key=lambda s: s.count)
    q = rng.normal(size=(n_queries, dim)).astype(np.float32)
    prior = PriorResult(Prior(big.centroid[0], big.centroid[1], "bench"), "bench")
    country16 = assemble_map(desc, c, ids, ident, {}, "country", index="fp16")
    out = {"src": src, "n": len(c), "submap_name": f"{big.id} ({big.count} refs)",
           "n_submaps": len(country.submaps), "partition_s": part_s}
    for name, m, cfg in (("submap", country, LocalizerConfig(top_p=top_p)),
                         ("submap_fp16", country16, LocalizerConfig(top_p=top_p)),
                         ("flat", flat, LocalizerConfig(top_p=top_p, use_submaps=False))):
        loc = Localizer(m, cfg)
        loc.localize(q[0], prior)
        times = []
        for x in q:
            t = time.perf_counter()
            hyp = loc.localize(x, prior)
            times.append(time.perf_counter() - t)
        out[name] = times
        out[name + "_hyp_submap"] = hyp.submap
    return out


def bench_submap_sizes(n_sub: int, dims: tuple[int, ...], n_queries: int, top_p: int) -> list:
    """Query time in one submap of exactly ``n_sub`` references, per dim and index type."""
    c, _ = coords(n_sub)
    rows = []
    rng = np.random.default_rng(2)
    for dim in dims:
        desc = rng.normal(size=(n_sub, dim)).astype(np.float32)
        desc /= np.linalg.norm(desc, axis=1, keepdims=True)
        ident = {"name": "synthetic", "dim": dim, "config": {}, "preprocessing": {}}
        q = rng.normal(size=(n_queries, dim)).astype(np.float32)
        prior = PriorResult(Prior(40.0, -100.0, "bench"), "bench")
        for kind in ("flat", "fp16"):
            m = assemble_map(desc, c, [f"r{i}" for i in range(n_sub)], ident, {}, "none",
                             index=kind)
            loc = Localizer(m, LocalizerConfig(top_p=top_p))
            loc.localize(q[0], prior)
            times = []
            for x in q:
                t = time.perf_counter()
                loc.localize(x, prior)
                times.append(time.perf_counter() - t)
            rows.append((dim, kind, times))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--refs", type=int, default=100_000)
    ap.add_argument("--dim", type=int, default=512)
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--top-p", type=int, default=50)
    ap.add_argument("--submap-size", type=int, default=41_000)
    a = ap.parse_args()
    import faiss

    print(f"threads: faiss {faiss.omp_get_max_threads()}, cores 2 (this machine)")
    f = bench_frames(a.frames)
    qb = bench_queries(a.refs, a.dim, a.queries, a.top_p)
    sub_med = statistics.median(qb["submap"])
    flat_med = statistics.median(qb["flat"])
    print()
    print("| measurement | value |")
    print("|---|---|")
    print(f"| vlad_rootsift descriptor, 640x480 frame | {ms(f['desc'])} |")
    print(f"| frame -> hypothesis (descriptor + country submap + re-rank), 640x480 | "
          f"{ms(f['frame'])} |")
    print(f"| map build (71 demo images, fit + describe + partition + write) | "
          f"{f['build_img_s']:.1f} images/s |")
    print(f"| country partition of {qb['n']} refs ({qb['src']}) | {qb['partition_s']:.1f} s, "
          f"{qb['n_submaps']} submaps |")
    print(f"| query in submap {qb['submap_name']}, {a.dim}-D float32, top-{a.top_p} + re-rank | "
          f"{ms(qb['submap'])} |")
    print(f"| same submap, `--index fp16` | {ms(qb['submap_fp16'])} |")
    print(f"| query flat global over {qb['n']} refs, {a.dim}-D, top-{a.top_p} + re-rank | "
          f"{ms(qb['flat'])} |")
    print(f"| flat / submap query time (same run) | {flat_med / sub_med:.2f}x |")
    for dim, kind, times in bench_submap_sizes(a.submap_size, (256, 512), a.queries, a.top_p):
        print(f"| query in a {a.submap_size}-ref submap, {dim}-D, index {kind}, "
              f"top-{a.top_p} + re-rank | {ms(times)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
