#!/usr/bin/env python3
"""Describing throughput: ``--engine local`` vs ``--engine ray`` with 1 and 2 workers, in one run.

    .venv/bin/python benchmarks/bench_ray.py                      # SF night database (332)
    .venv/bin/python benchmarks/bench_ray.py --limit 64           # quicker
    .venv/bin/python benchmarks/bench_ray.py --cost --limit 16    # per-worker cost table

Every engine describes the same images into its own shard folder with the same fitted state
(fitted once, beforehand, exactly as ``describe`` does), so the rows compare the describing
alone; the Ray rows start a local Ray with as many CPUs as workers. Printed: images/s of the
describe phase (with the actors' start-up) and end to end, the ratio to the local engine, and
the largest descriptor difference to the local engine (must be <= 1e-5).

``--cost``: images/s of ONE worker (one process, one thread) per descriptor, extrapolated to
4.1M images on 1 / 8 / 64 workers (linear scaling, as measured for 1 -> 2 workers above). The
deep models run with deterministic untrained weights: the same network, the same cost.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

from vlm_vpr_ros.descriptors import create_descriptor  # noqa: E402
from vlm_vpr_ros.distributed.describe import DescribeOptions, describe_to_shards  # noqa: E402
from vlm_vpr_ros.distributed.shards import ShardStore, job_fingerprint, read_shards  # noqa: E402
from vlm_vpr_ros.mapping.image_sources import ImageSource  # noqa: E402
from vlm_vpr_ros.mapping.build_images import fit_sample_indices  # noqa: E402
from vlm_vpr_ros.mapping.coords_csv import read_coords_csv  # noqa: E402

SF = REPO.parent / "shared" / "data" / "sf_night"
PLANET = 4_100_000
DEEP = ("cosplace", "eigenplaces", "mixvpr", "boq")


def prefit(images: str, ids: list[str], name: str, shard_size: int) -> dict:
    """Fit once (the describe job's sample) and return the state arrays."""
    from vlm_vpr_ros.distributed.engines import fit_on_sample

    desc = create_descriptor(name)
    if not desc.needs_fit:
        return {}
    sample = [ids[i] for i in fit_sample_indices(len(ids), desc)]
    return fit_on_sample(desc, ImageSource(images), sample)


def seed_folder(out: Path, ids: list[str], name: str, shard_size: int, state: dict) -> None:
    store = ShardStore(out)
    store.open(job_fingerprint(ids, create_descriptor(name).identity(), shard_size), len(ids),
               shard_size, overwrite=False)
    if state:
        store.save_state(state)


def engines(args, images: str, ids: list[str], tmp: Path) -> list[dict]:
    state = prefit(images, ids, args.descriptor, args.shard_size)
    runs = [("local", None), ("ray", 1), ("ray", 2)]
    rows, ref = [], None
    for engine, workers in runs:
        out = tmp / f"{engine}{workers or ''}"
        seed_folder(out, ids, args.descriptor, args.shard_size, state)
        opts = DescribeOptions(engine=engine, workers=workers, batch_size=args.batch_size,
                               shard_size=args.shard_size, progress=False,
                               ray_init={"object_store_memory": 200 * 1024 ** 2})
        t0 = time.monotonic()
        res = describe_to_shards(images, ids, out, args.descriptor, None, opts)
        wall = time.monotonic() - t0
        feats, ok = read_shards(out, ids)
        if ref is None:
            ref = (feats, ok)
        diff = float(np.abs(feats - ref[0]).max()) if (ok == ref[1]).all() else float("inf")
        rows.append({"engine": engine if engine == "local" else f"ray x{workers}",
                     "images": res.computed_images, "describe_ips": res.describe_images_per_s,
                     "wall_ips": res.computed_images / wall, "wall_s": wall, "diff": diff})
    return rows


def cost(args, images: str, ids: list[str], tmp: Path) -> list[dict]:
    """One worker = one process with one thread (what a Ray actor with num_cpus=1 gets)."""
    import torch

    from vlm_vpr_ros.descriptors.deep.weights import build_model, recipe_state_dict
    from vlm_vpr_ros.descriptors.deep import specs

    torch.set_num_threads(1)
    import cv2

    cv2.setNumThreads(1)
    out = []
    names = ["vlad_rootsift", "vlad_rootsift_fast", *DEEP]
    for name in names:
        cfg = {}
        if name in DEEP:
            weights = tmp / f"{name}.pth"
            torch.save(recipe_state_dict(build_model(specs.get_spec(name))), weights)
            cfg = {"weights": str(weights), "device": "cpu"}
        sub = ids[:args.cost_images]
        out_dir = tmp / f"cost_{name}"
        state = prefit(images, ids, name, args.shard_size) if name.startswith("vlad") else {}
        store = ShardStore(out_dir)
        store.open(job_fingerprint(sub, create_descriptor(name, cfg).identity(), 10 ** 6),
                   len(sub), 10 ** 6, overwrite=False)
        if state:
            store.save_state(state)
        opts = DescribeOptions(engine="local", batch_size=1, shard_size=10 ** 6, progress=False)
        res = describe_to_shards(images, sub, out_dir, name, cfg, opts)
        ips = res.describe_images_per_s
        out.append({"descriptor": name, "ips": ips,
                    **{f"h{w}": PLANET / (ips * w) / 3600 for w in (1, 8, 64)}})
        shutil.rmtree(out_dir, ignore_errors=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", default=str(SF))
    ap.add_argument("--coords", default=str(SF / "database.csv"))
    ap.add_argument("--descriptor", default="vlad_rootsift")
    ap.add_argument("--limit", type=int, default=0, help="first N images only (0: all)")
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--shard-size", type=int, default=64)
    ap.add_argument("--cost", action="store_true", help="per-descriptor cost table instead")
    ap.add_argument("--cost-images", type=int, default=16)
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    print(cpuinfo.cpu_line(), flush=True)
    logging.basicConfig(level=logging.WARNING)
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if not Path(args.coords).exists():
        print(f"{args.coords} not found (needs ../shared or --images/--coords)")
        return 2
    ids = [r[0] for r in read_coords_csv(args.coords)]
    if args.limit:
        ids = ids[:args.limit]
    tmp = Path(tempfile.mkdtemp(prefix="bench_ray_"))
    try:
        if args.cost:
            rows = cost(args, args.images, ids, tmp)
            print(f"\ncost per worker (1 CPU thread, this machine, {args.cost_images} SF night "
                  f"images), extrapolated to {PLANET:,} images")
            print(f"{'descriptor':<20}{'img/s/worker':>13}{'1 worker h':>12}{'8 workers h':>13}"
                  f"{'64 workers h':>14}")
            for r in rows:
                print(f"{r['descriptor']:<20}{r['ips']:>13.2f}{r['h1']:>12.0f}{r['h8']:>13.1f}"
                      f"{r['h64']:>14.2f}")
            return 0
        rows = engines(args, args.images, ids, tmp)
        base = rows[0]["describe_ips"]
        print(f"\n{args.descriptor} on {len(ids)} images of {args.images} "
              f"(os.cpu_count()={os.cpu_count()}, shared machine: compare ratios)")
        print(f"{'engine':<10}{'describe img/s':>15}{'ratio':>7}{'end-to-end img/s':>18}"
              f"{'wall s':>8}{'max |diff|':>12}")
        for r in rows:
            print(f"{r['engine']:<10}{r['describe_ips']:>15.2f}{r['describe_ips'] / base:>7.2f}"
                  f"{r['wall_ips']:>18.2f}{r['wall_s']:>8.1f}{r['diff']:>12.1e}")
        bad = [r for r in rows if not r["diff"] <= 1e-5]
        if bad:
            print("FAIL: descriptors differ from the local engine by more than 1e-5")
            return 1
        return 0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
