#!/usr/bin/env python3
"""Run the demo's tables under forced CPU code paths and compare them: the same demo on every
machine.

OpenCV, FAISS and OpenBLAS pick SIMD kernels for the CPU they run on (and OpenMP/OpenBLAS a
thread count), and the last bits of their arithmetic differ between kernels. The demo's tables
must not depend on them (vlm_vpr_ros/evaluation/demo.py, docs/evaluation.md "Same tables on
every machine"). This script runs ``run_demo`` (without the bag step, which repeats the demo
map's default row) once per setting below, each in a fresh process with the setting's
environment (the libraries read it when loaded), and compares every table of ``demo.json``
with the first setting's: it prints one line per setting and, for a table that differs, the
differing rows. Exit status 0: every table identical under every setting; 1: a difference; 2:
a run failed.

Usage::

    python scripts/check_cpu_paths.py                      # the whole demo (~2 CPU-min each)
    python scripts/check_cpu_paths.py --places 12          # a small case (tests use it)
    python scripts/check_cpu_paths.py --settings default,no-avx

The settings (``--list`` prints them): ``FAISS_SIMD_LEVEL`` is what FAISS >= 1.13 (one
library, dynamic dispatch) reads; ``FAISS_OPT_LEVEL`` is what older, per-level builds read; both
are set, and the line printed for each run says which FAISS level was in effect.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: name -> environment of the run (on top of the caller's)
SETTINGS: dict[str, dict[str, str]] = {
    "default": {},
    "1-thread": {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"},
    "2-threads": {"OMP_NUM_THREADS": "2", "OPENBLAS_NUM_THREADS": "2"},
    "no-avx": {"OPENCV_CPU_DISABLE": "AVX2,FMA3,AVX"},
    "generic-faiss-blas": {"FAISS_SIMD_LEVEL": "NONE", "FAISS_OPT_LEVEL": "generic",
                           "OPENBLAS_CORETYPE": "Prescott"},
    "all-forced": {"OPENCV_CPU_DISABLE": "AVX2,FMA3,AVX", "FAISS_SIMD_LEVEL": "NONE",
                   "FAISS_OPT_LEVEL": "generic", "OPENBLAS_CORETYPE": "Prescott",
                   "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"},
}
#: the variables a setting may change: removed from the caller's environment first
CONTROLLED = sorted({k for env in SETTINGS.values() for k in env})


def child(out: str, places: int | None) -> int:
    """One run in this process (called in a fresh interpreter with the setting's env)."""
    import contextlib
    import io

    import faiss
    from threadpoolctl import threadpool_info

    from vlm_vpr_ros.evaluation.demo import run_demo

    blas = ",".join(f"{i.get('internal_api')}:{i.get('architecture')}x{i.get('num_threads')}"
                    for i in threadpool_info())
    level = faiss.to_string(faiss.SIMDConfig.get_level()) if hasattr(
        faiss, "SIMDConfig") else "?"
    with contextlib.redirect_stdout(io.StringIO()):
        rc = run_demo(out, with_bag=False, places=places)
    Path(out, "paths.json").write_text(json.dumps({"faiss": level, "blas": blas}))
    return rc


def run_setting(name: str, out: Path, places: int | None, nice: int) -> tuple[dict, dict, float]:
    """(tables, code paths in effect, seconds) of one setting's run."""
    env = {k: v for k, v in os.environ.items() if k not in CONTROLLED}
    env.update(SETTINGS[name])
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(
        os.pathsep)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(out)]
    if places is not None:
        cmd += ["--places", str(places)]
    if nice:
        cmd = ["nice", "-n", str(nice), *cmd]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    dt = time.monotonic() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"setting {name}: the demo failed (exit {proc.returncode}):\n"
                           + proc.stderr[-2000:])
    doc = json.loads((out / "demo.json").read_text(encoding="utf-8"))
    paths = json.loads((out / "paths.json").read_text(encoding="utf-8"))
    return doc["tables"], paths, dt


def differences(ref: dict, got: dict) -> list[str]:
    """Lines naming every table row that differs (or is missing) between two runs."""
    out = []
    for table in sorted(set(ref) | set(got)):
        a, b = ref.get(table), got.get(table)
        if a == b:
            continue
        if a is None or b is None:
            out.append(f"  {table}: only in {'the first' if b is None else 'this'} run")
            continue
        if a.get("columns") != b.get("columns"):
            out.append(f"  {table}: columns differ: {a.get('columns')} / {b.get('columns')}")
        rows_a = {r[0]: r for r in a.get("rows", [])}
        rows_b = {r[0]: r for r in b.get("rows", [])}
        for label in dict.fromkeys([*rows_a, *rows_b]):
            if rows_a.get(label) != rows_b.get(label):
                out.append(f"  {table} / {label}:\n    first: {rows_a.get(label)}\n"
                           f"    this:  {rows_b.get(label)}")
    return out


def compare(names: list[str], places: int | None, work: Path, nice: int = 10,
            echo=print) -> tuple[bool, list[dict]]:
    """Run every named setting and compare with the first; (all identical, per-run facts)."""
    runs, first = [], None
    for name in names:
        tables, paths, dt = run_setting(name, work / name, places, nice)
        diff = [] if first is None else differences(first, tables)
        first = tables if first is None else first
        env = " ".join(f"{k}={v}" for k, v in SETTINGS[name].items()) or "(as the machine is)"
        echo(f"{name:<20} {dt:6.0f} s  faiss {paths['faiss']:<15} {paths['blas']:<28} "
             f"{'reference' if len(runs) == 0 else ('identical' if not diff else 'DIFFERENT')}"
             f"\n{'':<29}{env}")
        for line in diff:
            echo(line)
        runs.append({"setting": name, "seconds": round(dt, 1), "identical": not diff,
                     **paths, "diff": diff})
    return all(r["identical"] for r in runs), runs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Run the demo's tables under forced CPU code paths "
                                            "(SIMD, BLAS kernel, threads) and compare them.")
    p.add_argument("--places", type=int, default=None, metavar="N",
                   help="only the first N shipped images (default: all 71, ~2 CPU-min a run)")
    p.add_argument("--settings", default=",".join(SETTINGS), metavar="A,B,...",
                   help="settings to run, the first is the reference (default: all)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="keep the runs here (default: a temporary folder, removed)")
    p.add_argument("--nice", type=int, default=10, help="niceness of the runs (default 10)")
    p.add_argument("--list", action="store_true", help="print the settings and exit")
    p.add_argument("--child", default=None, metavar="OUT", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return child(args.child, args.places)
    if args.list:
        for name, env in SETTINGS.items():
            print(f"{name:<20} {' '.join(f'{k}={v}' for k, v in env.items()) or '-'}")
        return 0
    names = [s for s in args.settings.split(",") if s]
    unknown = [s for s in names if s not in SETTINGS]
    if unknown or len(names) < 2:
        p.error(f"--settings: two or more of {', '.join(SETTINGS)} (got {args.settings!r})")
    if args.places is not None and args.places < 3:
        p.error("--places must be at least 3")
    with tempfile.TemporaryDirectory(prefix="cpu_paths_") as tmp:
        work = Path(args.out) if args.out else Path(tmp)
        try:
            same, _ = compare(names, args.places, work, args.nice)
        except RuntimeError as exc:
            print(f"check_cpu_paths: {exc}", file=sys.stderr)
            return 2
    print("every table identical under every setting" if same
          else "tables DIFFER between settings", flush=True)
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
