#!/usr/bin/env python3
"""``vlm-vpr evaluate`` on a large results CSV: wall time and peak memory against the targets
of issue 28 (2,000,000 rows in <= 60 s and <= 500 MB).

Generates a results CSV of N rows (``file, lat, lon, uncertainty_m, status, flags``: a
fix within ~100 m of the truth for 70 % of the rows, a wrong place for 25 %, no estimate for
5 %, and a few junk rows) and its ground truth, then runs ``vlm-vpr evaluate --json`` in a
child process, which reports its own peak resident memory (``VmHWM``), and its CPU time.

    .venv/bin/python benchmarks/bench_evaluate.py [--rows 2000000] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
TARGET_S, TARGET_MB = 60.0, 500.0
#: the child: the CLI, then its own peak resident memory (VmHWM of /proc/self/status; not
#: getrusage's maxrss, which on Linux keeps the parent's RSS from before the child's exec)
CHILD = ("import sys\nfrom vlm_vpr_ros.cli import main\nrc = main(sys.argv[1:])\n"
         "hwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM')]\n"
         "sys.stderr.write('\\n' + hwm[0])\nsys.exit(rc)")


def peak_mb(stderr: str) -> float:
    """The child's peak resident memory (MB) from the VmHWM line it wrote on stderr."""
    return int(stderr.rsplit("VmHWM:", 1)[1].split()[0]) / 1024.0


def generate(folder: Path, n: int, seed: int = 0) -> tuple[Path, Path]:
    rng = np.random.default_rng(seed)
    lat = rng.uniform(-60, 70, n)
    lon = rng.uniform(-180, 180, n)
    kind = rng.random(n)
    elat = np.where(kind < 0.70, lat + rng.normal(0, 0.0005, n), rng.uniform(-60, 70, n))
    elon = np.where(kind < 0.70, lon + rng.normal(0, 0.0005, n), rng.uniform(-180, 180, n))
    elon = (elon + 180.0) % 360.0 - 180.0  # near the antimeridian: stay in range
    gt, res = folder / "gt.csv", folder / "results.csv"
    step = 200_000
    with open(gt, "w") as g, open(res, "w") as r:
        g.write("file,lat,lon\n")
        r.write("file,lat,lon,uncertainty_m,status,flags\n")
        for a in range(0, n, step):
            b = min(n, a + step)
            g.write("".join(f"q{i:07d}.jpg,{lat[i]:.5f},{lon[i]:.5f}\n" for i in range(a, b)))
            lines = []
            for i in range(a, b):
                if kind[i] >= 0.95:
                    lines.append(f"q{i:07d}.jpg,,,,no_fix,no_match\n")
                elif i % 100_000 == 7:  # junk: counted, not scored
                    lines.append(f"q{i:07d}.jpg,91,{lon[i]:.5f},30,fix,\n")
                else:
                    st = "fix" if kind[i] < 0.70 else "no_fix"
                    lines.append(f"q{i:07d}.jpg,{elat[i]:.5f},{elon[i]:.5f},30,{st},\n")
            r.write("".join(lines))
    return res, gt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=2_000_000)
    ap.add_argument("--keep", default=None, help="write the CSVs here (else a temp folder)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        res, gt = generate(folder, args.rows)
        print(f"generated {args.rows:,} rows: results {res.stat().st_size / 1e6:.1f} MB, "
              f"ground truth {gt.stat().st_size / 1e6:.1f} MB ({time.monotonic() - t0:.1f} s)")
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        t0 = time.monotonic()
        proc = subprocess.run([sys.executable, "-c", CHILD, "evaluate", "--results", str(res),
                               "--ground-truth", str(gt), "--json"],
                              capture_output=True, text=True, env=env)
        wall = time.monotonic() - t0
        use = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = use.ru_utime + use.ru_stime
    if proc.returncode != 0:
        print(proc.stderr, file=sys.stderr)
        return 1
    peak = peak_mb(proc.stderr)
    out = json.loads(proc.stdout)
    print(f"evaluate: n {out['n']:,}, junk rows {out['junk_rows']}, accuracy "
          f"{out['accuracy']}, fixes {out['fixes']['n']:,}")
    ok_t, ok_m = wall <= TARGET_S, peak <= TARGET_MB
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; CPU time "
          f"{cpu:.1f} s")
    print(f"time {wall:.1f} s (target <= {TARGET_S:.0f} s: {'ok' if ok_t else 'MISSED'}); "
          f"peak RSS {peak:.0f} MB (target <= {TARGET_MB:.0f} MB: "
          f"{'ok' if ok_m else 'MISSED'})")
    return 0 if ok_t and ok_m else 1


if __name__ == "__main__":
    sys.exit(main())
