#!/usr/bin/env python3
"""Core speed benchmark (CPU): descriptor time per 640x480 frame, map build rate, frame -> fix on
a 100k-reference map, and retrieval + fusion per query for both fusion modes on that map
against one global search, all measured in this one run.

The 100k maps are synthetic descriptors (random unit vectors) at the 100k real MP-16 positions of
../shared/data/mp16_coords (random positions if that folder is absent), one submap per country,
saved and opened from disk as the node opens a map (memory-mapped). Query rows are timed
round-robin (query i in every mode before query i+1), so a change in machine load hits every
row alike, in a random order per query (a mode run right after another on the same query finds
rows in the caches: no mode always runs first); "submaps searched" and "references scanned" are
counted on one extra query by wrapping every submap's search (a submap searched twice counts
twice).

    .venv/bin/python benchmarks/bench_core.py [--refs 100000] [--dim 512] [--queries 200]
        [--json bench_core.json]

``--json PATH`` writes every row (name as printed, numbers) for tools that regenerate the
docs' tables; row names are stable.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

from vlm_vpr_ros.descriptors import create_descriptor  # noqa: E402
from vlm_vpr_ros.evaluation.demo import DEMO_DATA, make_query  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig  # noqa: E402
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline  # noqa: E402
from vlm_vpr_ros.mapping.assemble import assemble_map  # noqa: E402
from vlm_vpr_ros.mapping.build_images import build_map  # noqa: E402
from vlm_vpr_ros.maps.reference_map import ReferenceMap  # noqa: E402
from vlm_vpr_ros.priors.provider import Prior, PriorResult  # noqa: E402

SHARED = Path(os.environ.get("VLM_VPR_SHARED", REPO.parent / "shared"))
MP16 = SHARED / "data" / "mp16_coords" / "coordinates_100K.csv"
DEFAULT_DESCRIPTOR = "vlad_rootsift"  # build-map's default
SEARCHES = ("search", "searchable", "pq_candidates")  # a submap's scans (maps/search.py)


def stats(samples: list[float]) -> dict:
    s = sorted(samples)
    return {"median_ms": round(statistics.median(s) * 1e3, 3),
            "p95_ms": round(s[int(0.95 * (len(s) - 1))] * 1e3, 3), "n": len(s)}


def ms(st: dict) -> str:
    return f"{st['median_ms']:8.2f} ms (p95 {st['p95_ms']:.2f})"


def coords(n: int) -> tuple[np.ndarray, str]:
    if MP16.is_file():
        with MP16.open() as fh:
            rows = [(float(r["LAT"]), float(r["LON"])) for r in csv.DictReader(fh)]
        c = np.array(rows[:n])
        if len(c) >= n:
            return c, f"MP-16 ({len(c)} real positions)"
    rng = np.random.default_rng(0)
    return np.stack([rng.uniform(-60, 70, n), rng.uniform(-180, 180, n)], 1), "random positions"


def synthetic_map(tmp: Path, name: str, c: np.ndarray, dim: int, partition: str,
                  index: str = "flat", identity: dict | None = None,
                  state: dict | None = None, seed: int = 1) -> ReferenceMap:
    """Random unit descriptors at positions ``c``, saved and re-opened (v2, memory-mapped)."""
    rng = np.random.default_rng(seed)
    desc = rng.normal(size=(len(c), dim)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    ident = identity or {"name": "synthetic", "dim": dim, "config": {}, "preprocessing": {}}
    m = assemble_map(desc, c, [f"r{i}" for i in range(len(c))], ident, state or {}, partition,
                     index=index)
    m.save(tmp / name)
    return ReferenceMap.load(tmp / name)


def scanned(loc: Localizer, q: np.ndarray, prior: PriorResult | None) -> dict:
    """What one localize() call scans: submaps (a submap scanned twice counts twice), FAISS
    index searches (the small submaps' pooled copy is one per kind) and references."""
    seen = {"submaps": 0, "searches": 0, "refs": 0}
    hooked = []
    for s in loc.map.submaps:
        for name in SEARCHES:
            orig = getattr(s, name)

            def spy(*a, _orig=orig, _n=s.count):
                seen["submaps"] += 1
                seen["searches"] += 1
                seen["refs"] += _n
                return _orig(*a)
            setattr(s, name, spy)
            hooked.append((s, name))
    small = getattr(loc.map, "small_submaps", None)  # absent before issue 23
    if small is not None:
        pool = small()
        orig_hits = pool.hits

        def pooled(*a, _orig=orig_hits, _pool=pool):
            seen["submaps"] += int(_pool.pooled.sum())
            seen["searches"] += len(_pool.parts)
            seen["refs"] += _pool.n_refs
            return _orig(*a)
        pool.hits = pooled
        hooked.append((pool, "hits"))
    try:
        loc.localize(q, prior)
    finally:
        for obj, name in hooked:
            delattr(obj, name)
    return seen


def bench_frames(tmp: Path, n_frames: int, c: np.ndarray) -> dict:
    """Demo map build rate, then frame -> fix with the default descriptor at its full size
    (fitted on the demo images and three augmented views of each: 284 images, enough for its
    256-D PCA; the 71-image demo map alone gives 70-D) on a map of its size at positions ``c``
    (synthetic descriptors, country submaps), default (posterior) fusion, VLM-like prior."""
    images = sorted((DEMO_DATA / "images").glob("*.jpg"))
    t0 = time.perf_counter()
    build_map(DEMO_DATA / "images", DEMO_DATA / "coords.csv", tmp / "demo",
              partition="country", progress=False)
    build_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    fit = [load_image(f) for f in images]
    fit += [make_query(im, rng) for im in fit for _ in range(3)]
    descriptor = create_descriptor(DEFAULT_DESCRIPTOR)
    descriptor.fit(fit, progress=False)
    big = synthetic_map(tmp, "frame_map", c, descriptor.dim, "country",
                        identity=descriptor.identity(), state=descriptor.state_arrays())
    pipe = LocalizationPipeline(big, descriptor, Localizer(big, LocalizerConfig()))
    us = max(big.submaps, key=lambda s: s.count)
    prior = PriorResult(Prior(us.centroid[0], us.centroid[1], "bench"), "bench")
    frames = [make_query(load_image(f), np.random.default_rng(i))
              for i, f in enumerate(images[:n_frames])]
    assert frames[0].shape == (480, 640, 3)
    pipe.localize_image(frames[0], prior)  # warm-up
    total, desc_s, fix_s = [], [], []
    for fr in frames:
        t0 = time.perf_counter()
        hyp = pipe.localize_image(fr, prior)
        total.append(time.perf_counter() - t0)
        desc_s.append(hyp.timings_ms["descriptor_ms"] / 1e3)
        fix_s.append((hyp.timings_ms["retrieval_ms"] + hyp.timings_ms["rerank_ms"]) / 1e3)
    return {"build_img_s": len(images) / build_s, "dim": big.dim, "n": big.n_references,
            "desc": stats(desc_s), "frame": stats(total), "fix": stats(fix_s),
            "descriptor": descriptor.name}


def bench_modes(tmp: Path, c: np.ndarray, src: str, dim: int, n_queries: int,
                top_p: int) -> dict:
    """Retrieval + fusion per query, every mode round-robin on the same queries."""
    t0 = time.perf_counter()
    country = synthetic_map(tmp, "country", c, dim, "country")
    part_s = time.perf_counter() - t0
    country16 = synthetic_map(tmp, "country16", c, dim, "country", index="fp16")
    flat = synthetic_map(tmp, "flat", c, dim, "none")
    us_i = max(range(len(country.submaps)), key=lambda i: country.submaps[i].count)
    us = country.submaps[us_i]
    at = us.centroid
    vlm = PriorResult(Prior(at[0], at[1], "bench"), "bench")  # pooled VLM error model
    s25 = PriorResult(Prior(at[0], at[1], "bench", 25.0), "bench")
    post, paper = LocalizerConfig(top_p=top_p), LocalizerConfig(top_p=top_p, fusion="paper")
    us_name = f"{us.id}, {us.count:,} refs"
    modes = [  # (row name, localizer, prior, key)
        ("posterior, VLM-like prior (pooled error model) at the US centroid",
         Localizer(country, post), vlm, "posterior_vlm"),
        ("posterior, prior with sigma_km = 25 at the US centroid",
         Localizer(country, post), s25, "posterior_sigma25"),
        ("posterior, no prior", Localizer(country, post), None, "posterior_no_prior"),
        (f"paper, prior at the US centroid: one submap ({us_name})",
         Localizer(country, paper), vlm, "paper"),
        (f"paper, same submap, fp16 index ({us_name})", Localizer(country16, paper), vlm,
         "paper_fp16"),
        (f"one global search: one flat index over all {len(c):,} refs, posterior fusion, "
         "VLM-like prior", Localizer(flat, LocalizerConfig(top_p=top_p, use_submaps=False)),
         vlm, "global_flat"),
    ]
    rng = np.random.default_rng(2)
    q = rng.normal(size=(n_queries + 1, dim)).astype(np.float32)
    rows = {}
    for name, loc, pr, key in modes:
        region, _ = loc.select_submaps(pr.prior if pr else None)
        seen = scanned(loc, q[0], pr)
        rows[key] = {"name": name, "region_submaps": len(region),
                     "submaps_searched": seen["submaps"], "faiss_searches": seen["searches"],
                     "refs_scanned": seen["refs"], "times": []}
    order = list(modes)
    shuffle = random.Random(0).shuffle
    for x in q[1:]:
        shuffle(order)
        for _, loc, pr, key in order:
            t = time.perf_counter()
            loc.localize(x, pr)
            rows[key]["times"].append(time.perf_counter() - t)
    threads = threads_rows(flat.submaps[0].index, q[1:], top_p)
    base = statistics.median(rows["global_flat"]["times"])
    for r in rows.values():
        r.update(stats(r.pop("times")))
        r["vs_global"] = round(r["median_ms"] / (base * 1e3), 3)
    return {"src": src, "n": len(c), "dim": dim, "n_submaps": len(country.submaps),
            "partition_s": part_s, "rows": rows, "threads": threads}


def threads_rows(index, queries: np.ndarray, top_p: int) -> dict:
    """FAISS's search alone on one flat index, with its OpenMP default and with the one thread
    a localizer query uses (maps/search.py), alternated query by query (each first on every
    other query)."""
    import faiss

    default = faiss.omp_get_max_threads()
    times: dict[int, list[float]] = {default: [], 1: []}
    for i, x in enumerate(queries):
        for n in (list(times) if i % 2 else list(times)[::-1]):
            faiss.omp_set_num_threads(n)
            t = time.perf_counter()
            index.search(x[None, :], top_p)
            times[n].append(time.perf_counter() - t)
    faiss.omp_set_num_threads(default)
    return {n: stats(t) for n, t in times.items()}


def bench_submap_sizes(tmp: Path, n_sub: int, dims: tuple[int, ...], n_queries: int,
                       top_p: int) -> list:
    """Retrieval + fusion in a map that is one submap of exactly ``n_sub`` references."""
    c, _ = coords(n_sub)
    rows = []
    rng = np.random.default_rng(2)
    prior = PriorResult(Prior(40.0, -100.0, "bench"), "bench")
    for dim in dims:
        q = rng.normal(size=(n_queries, dim)).astype(np.float32)
        for kind in ("flat", "fp16"):
            m = synthetic_map(tmp, f"one_{dim}_{kind}", c, dim, "none", index=kind, seed=dim)
            loc = Localizer(m, LocalizerConfig(top_p=top_p))
            loc.localize(q[0], prior)
            times = []
            for x in q:
                t = time.perf_counter()
                loc.localize(x, prior)
                times.append(time.perf_counter() - t)
            rows.append((dim, kind, stats(times)))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--refs", type=int, default=100_000)
    ap.add_argument("--dim", type=int, default=512)
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--top-p", type=int, default=50)
    ap.add_argument("--submap-size", type=int, default=41_000)
    ap.add_argument("--json", type=Path, default=None, help="also write the rows as JSON here")
    ap.add_argument("--node-malloc", action="store_true",
                    help="glibc malloc as the node sets it (vlm_vpr_ros/ros/malloc.py)")
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    a = ap.parse_args()
    if a.node_malloc:
        print(cpuinfo.node_malloc())
    print(cpuinfo.cpu_line(), flush=True)
    import faiss

    load = os.getloadavg()
    print(f"threads: faiss {faiss.omp_get_max_threads()}, cores {os.cpu_count()}; load average "
          f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}")
    c, src = coords(a.refs)
    table: dict[str, dict] = {}

    def row(name: str, text: str, **numbers) -> None:
        table[name] = {"value": text.strip(), **numbers}
        print(f"| {name} | {text} |")

    with tempfile.TemporaryDirectory() as tmp:
        f = bench_frames(Path(tmp), a.frames, c)
        qb = bench_modes(Path(tmp), c, src, a.dim, a.queries, a.top_p)
        sizes = bench_submap_sizes(Path(tmp), a.submap_size, (256, 512), a.queries, a.top_p)
    print()
    print("| measurement | value |")
    print("|---|---|")
    row(f"{f['descriptor']} descriptor, 640x480 frame", ms(f["desc"]), **f["desc"])
    row(f"map build (71 demo images, fit + describe + partition + write)",
        f"{f['build_img_s']:.1f} images/s", images_per_s=round(f["build_img_s"], 2))
    row(f"frame -> fix, 640x480: {f['descriptor']} ({f['dim']}-D) + posterior fusion, "
        f"VLM-like prior, {f['n']:,}-ref country-submap map (no local features: "
        f"verification off)", ms(f["frame"]), **f["frame"])
    row("  of which retrieval + fusion", ms(f["fix"]), **f["fix"])
    row(f"country partition of {qb['n']} refs ({qb['src']})",
        f"{qb['partition_s']:.1f} s, {qb['n_submaps']} submaps",
        seconds=round(qb["partition_s"], 2), submaps=qb["n_submaps"])
    for dim, kind, st in sizes:
        row(f"retrieval + fusion, one {a.submap_size}-ref submap, {dim}-D, index {kind}, "
            f"top-{a.top_p}", ms(st), **st)
    print(f"\nretrieval + fusion per query, {qb['n']:,} refs, {qb['dim']}-D float32 (unless "
          f"noted), {qb['n_submaps']} country submaps, top-{a.top_p}; {a.queries} queries, "
          f"modes timed round-robin; last column: median / the one global search's median")
    print("| mode | region (submaps) | submaps searched | FAISS searches | references scanned "
          "| median ms (p95) | / one global search |")
    print("|---|---|---|---|---|---|---|")
    for key, r in qb["rows"].items():
        table[r["name"]] = {"value": ms(r).strip(), "key": key, **{
            k: v for k, v in r.items() if k != "name"}}
        print(f"| {r['name']} | {r['region_submaps']} | {r['submaps_searched']} | "
              f"{r['faiss_searches']} | {r['refs_scanned']:,} | {ms(r)} | "
              f"{r['vs_global']:.2f}x |")
    for n, st in qb["threads"].items():
        name = (f"FAISS search alone, the flat index of {qb['n']:,} refs, "
                + ("1 OpenMP thread (as in a localizer query)" if n == 1 else
                   f"OpenMP default ({n} threads)"))
        table[name] = {"value": ms(st).strip(), "threads": n, **st}
        print(f"| {name} | | | 1 | {qb['n']:,} | {ms(st)} | |")
    rows = qb["rows"]
    print("\n| target (same run) | measured | status |")
    print("|---|---|---|")
    for key, what in (("posterior_vlm", "posterior, VLM-like prior"),
                      ("posterior_sigma25", "posterior, sigma_km = 25 prior")):
        v = rows[key]["vs_global"]
        name = f"{what} / one global search <= 1.2x"
        table[name] = {"value": f"{v:.2f}x", "ratio": v, "target": 1.2}
        print(f"| {name} | {v:.2f}x | {'met' if v <= 1.2 else 'MISSED'} |")
    fr = f["frame"]["median_ms"]
    name = (f"frame -> fix (descriptor + posterior fusion) on the {f['n']:,}-ref map "
            "<= 100 ms median")
    table[name] = {"value": f"{fr:.1f} ms", "median_ms": fr, "target_ms": 100.0}
    print(f"| {name} | {fr:.1f} ms | {'met' if fr <= 100 else 'MISSED'} |")
    if a.json:
        a.json.write_text(json.dumps({
            "benchmark": "benchmarks/bench_core.py", "args": {k: str(v) for k, v in
                                                             vars(a).items()},
            "machine": {"cores": os.cpu_count(), "faiss_threads": faiss.omp_get_max_threads(),
                        "cpuinfo": cpuinfo.describe(),
                        "load_average": [round(x, 2) for x in load]},
            "rows": table}, indent=1) + "\n")
        print(f"\nwrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
