#!/usr/bin/env python3
"""What the content check costs when a map is opened (issue 19): ``ReferenceMap.load`` with and
without :func:`vlm_vpr_ros.maps.format.check_content`, in one run, warm and cold page cache.

The check reads only a few pages per file (small files whole), so its cost depends on the
number of files and their sizes, not on their contents. By default the map is a synthetic
folder with the layout of the 4.1M-reference pq map of docs/planet_scale.md (166 submaps of
~24,700 references: index 3.2 MB, fp16 vectors 25 MB, coords 0.4 MB, ids 0.6 MB each, 4.5 GB
in all), written *sparse*: only the bytes the check reads (sampled pages, small files) are
written, so the folder takes ~25 MB of disk while every read the check makes hits real data.
``--map PATH`` measures a real map instead. "Cold" evicts the map's files from the page cache
first (``posix_fadvise(DONTNEED)`` on each file: only this map's pages, nothing system-wide).

    .venv/bin/python benchmarks/bench_open_check.py [--submaps 166] [--refs 4100000]
        [--map PATH] [--repeat 5] [--workdir /tmp/bench_open_check]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402


def make_map(out: Path, n_submaps: int, n_refs: int, dim: int = 512) -> None:
    """A v2 folder with the 4.1M pq map's file layout, sparse except for what is checked."""
    import numpy as np

    from vlm_vpr_ros.maps.format import (MAP_FORMAT, METRIC, SMALL_FILE_BYTES, file_entry,
                                         sample_offsets, PAGE_BYTES)

    rng = np.random.default_rng(0)
    shutil.rmtree(out, ignore_errors=True)
    (out / "submaps").mkdir(parents=True)
    per = n_refs // n_submaps
    sizes = {"index": per * dim // 4 + 65_000, "vectors": per * dim * 2 + 128,
             "coords": per * 16 + 128, "ids": per * 24 + 128}
    suffix = {"index": ".faiss", "vectors": ".f16.npy", "coords": ".coords.npy",
              "ids": ".ids.npy"}
    subs, files = [], {}
    for k in range(n_submaps):
        sid = f"k{k:03d}"
        rel = {role: f"submaps/{sid}{suffix[role]}" for role in sizes}
        for role, size in sizes.items():
            p = out / rel[role]
            with open(p, "wb") as fh:
                fh.truncate(size)
                chunks = [0] if size <= SMALL_FILE_BYTES else sample_offsets(size)
                for off in chunks:
                    fh.seek(off)
                    fh.write(rng.bytes(min(size - off, SMALL_FILE_BYTES if size <=
                                           SMALL_FILE_BYTES else PAGE_BYTES)))
            files[rel[role]] = file_entry(out, rel[role])
        subs.append({"id": sid, "group": sid, "count": per, "kind": "pq",
                     "centroid": [float(rng.uniform(-50, 60)), float(rng.uniform(-180, 180))],
                     "radius_km": 50.0, "files": rel})
    manifest = {"format": MAP_FORMAT, "version": 2, "metric": METRIC,
                "descriptor": {"name": "cosplace", "dim": dim}, "partition": {"method":
                                                                             "kmeans"},
                "n_references": per * n_submaps, "n_submaps": n_submaps, "index": "pq",
                "index_params": {"rerank_factor": 16}, "descriptor_state": None,
                "submaps": subs, "files": files}
    (out / "manifest.json").write_text(json.dumps(manifest))


def evict(path: Path) -> None:
    for p in path.rglob("*"):
        if p.is_file():
            fd = os.open(p, os.O_RDONLY)
            try:
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            finally:
                os.close(fd)


def time_open(path: Path, check: bool, cold: bool, repeat: int) -> float:
    from vlm_vpr_ros.maps import store
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    real = store.check_content
    if not check:
        store.check_content = lambda *a, **k: 0
    try:
        times = []
        for _ in range(repeat):
            if cold:
                evict(path)
            t0 = time.perf_counter()
            ReferenceMap.load(path)
            times.append(time.perf_counter() - t0)
    finally:
        store.check_content = real
    return statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", type=Path, default=None, help="measure this map instead")
    ap.add_argument("--submaps", type=int, default=166)
    ap.add_argument("--refs", type=int, default=4_100_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_open_check"))
    ap.add_argument("--keep", action="store_true")
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    print(cpuinfo.cpu_line(), flush=True)
    path = args.map
    if path is None:
        path = args.workdir / "map"
        make_map(path, args.submaps, args.refs)
    man = json.loads((path / "manifest.json").read_text())
    from vlm_vpr_ros.maps.format import SMALL_FILE_BYTES, sample_offsets

    n_files = sum(len(s["files"]) for s in man["submaps"])
    read = sum(m["bytes"] if m["bytes"] <= SMALL_FILE_BYTES else
               4096 * len(sample_offsets(m["bytes"])) for m in man["files"].values())
    total = sum(m["bytes"] for m in man["files"].values())
    print(f"map {path}: {man['n_references']:,} references, {len(man['submaps'])} submaps, "
          f"{n_files} files, {total / 2**30:.2f} GiB; the check reads {read / 2**20:.1f} MiB")
    print(f"load: {os.getloadavg()[0]:.1f} (1-min average) on {os.cpu_count()} CPUs")
    print(f"{'':<34}{'no content check':>18}{'content check':>16}{'ratio':>8}")
    for cold in (False, True):
        off = time_open(path, False, cold, args.repeat)
        on = time_open(path, True, cold, args.repeat)
        print(f"{'open map, ' + ('cold' if cold else 'warm') + ' cache (s, median)':<34}"
              f"{off:>18.3f}{on:>16.3f}{on / off:>7.2f}x")
    if args.map is None and not args.keep:
        shutil.rmtree(args.workdir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
