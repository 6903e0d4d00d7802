#!/usr/bin/env python3
"""Bag reading speed (issue 30): the old hand-written reader vs the rosbags path of
``vlm_vpr_ros.bags.reader`` and its hand-written recovery reader, on one bag per storage.

The bag is written by the project's writer (rosbags): ``--messages`` messages (default 3000) on
three topics, one in six a ~``--image-kb`` kB payload (a compressed camera frame), the rest
300-byte ones (IMU-like), 100 Hz with equal stamps across topics. Each reader opens the bag
and reads every message (``open_bag`` + ``messages()``); the time is the median of
``--repeat`` runs, warm page cache. The old reader is ``vlm_vpr_ros/bags/reader.py`` at git
revision ``--old`` (the last commit before the rosbags path), loaded from git; every reader's
output is checked to be identical (topic, type, time, bytes, order) before timing.

    .venv/bin/python benchmarks/bench_bag_read.py [--messages 3000] [--image-kb 30]
        [--repeat 5] [--old 2fc2074] [--workdir /tmp/bench_bag_read]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

TYPE = "std_msgs/msg/String"


def make(path: Path, storage: str, compression: str, n: int, image_kb: int) -> int:
    from vlm_vpr_ros.bags.writer import BagWriter

    topics = ("/imu", "/gps", "/camera")
    with BagWriter(path, storage=storage, compression=compression, overwrite=True) as w:
        for t in topics:
            w.add_topic(t, TYPE)
        for i in range(n):
            size = image_kb * 1000 if i % 6 == 0 else 300
            raw = os.urandom(size // 2).hex()[:size].encode() + b"\x00"
            data = b"\x00\x01\x00\x00" + len(raw).to_bytes(4, "little") + raw
            w.write(topics[i % 3], data, 1_700_000_000_000_000_000 + (i // 3) * 10_000_000)
    return sum(f.stat().st_size for f in path.iterdir())


def load_old(rev: str, workdir: Path):
    """``bags/reader.py`` as of ``rev`` as a module, or None when git cannot give it."""
    try:
        text = subprocess.run(["git", "-C", str(REPO), "show",
                               f"{rev}:vlm_vpr_ros/bags/reader.py"],
                              check=True, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    src = workdir / "old_reader.py"
    src.write_text(text)
    spec = importlib.util.spec_from_file_location("old_bag_reader", src)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # (dataclasses look their module up)
    spec.loader.exec_module(mod)
    return mod


def read_all(open_fn, path: Path) -> list:
    return [(m.topic, m.type, m.log_time_ns, m.data) for m in open_fn(path).messages()]


def timed(open_fn, path: Path, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        n = sum(len(m.data) for m in open_fn(path).messages())
        times.append(time.perf_counter() - t0)
        assert n > 0
    return statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=3000)
    ap.add_argument("--image-kb", type=int, default=30)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--old", default="2fc2074", help="git revision of the old reader")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_bag_read"))
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    print(cpuinfo.cpu_line(), flush=True)
    from vlm_vpr_ros.bags.reader import open_bag

    args.workdir.mkdir(parents=True, exist_ok=True)
    old = load_old(args.old, args.workdir)
    readers = {"old (hand-written)": old.open_bag if old else None,
               "new: rosbags": open_bag,
               "new: recovery reader": lambda p: open_bag(p, recovery=True)}
    print(f"load: {os.getloadavg()[0]:.1f} (1-min average) on {os.cpu_count()} CPUs; "
          f"{args.messages} messages, median of {args.repeat} reads (s)")
    head = f"{'bag':<16}{'MB':>7}" + "".join(f"{k:>22}" for k in readers) + f"{'old/rosbags':>13}"
    print(head)
    for storage, comp in (("mcap", "none"), ("mcap", "zstd"), ("sqlite3", "none")):
        path = args.workdir / f"{storage}_{comp}"
        size = make(path, storage, comp, args.messages, args.image_kb)
        ref = read_all(open_bag, path)
        assert len(ref) == args.messages
        row, secs = f"{storage + (' zstd' if comp != 'none' else ''):<16}{size / 1e6:>7.1f}", {}
        for name, fn in readers.items():
            if fn is None:
                row += f"{'(no git)':>22}"
                continue
            assert read_all(fn, path) == ref, f"{name} reads {path} differently"
            secs[name] = timed(fn, path, args.repeat)
            row += f"{secs[name]:>10.3f} s {args.messages / secs[name]:>7.0f}/s"
        old_s = secs.get("old (hand-written)")
        row += f"{old_s / secs['new: rosbags']:>12.2f}x" if old_s else f"{'':>13}"
        print(row, flush=True)
    print("all readers gave identical messages (topic, type, time, bytes) in identical order")
    shutil.rmtree(args.workdir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
