"""benchmarks/bench_retrieval.py: without data it says so and exits 0; on a tiny SF-night-like
folder made of shipped demo images it prints one markdown table of the documented shape."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BENCH = [sys.executable, str(REPO / "benchmarks" / "bench_retrieval.py")]


def _run(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return subprocess.run([*BENCH, *args], capture_output=True, text=True, timeout=600,
                          env=env)


def test_no_data_nothing_measured(tmp_path):
    proc = _run("--data", str(tmp_path / "absent"))
    assert proc.returncode == 0
    assert proc.stdout.strip() == "no SF night data; nothing measured"


def test_table_shape_on_a_tiny_folder(tmp_path, demo_data):
    rows = list(csv.DictReader(open(demo_data / "coords.csv")))[:10]
    root = tmp_path / "sf"
    for part in ("database", "queries"):
        (root / part).mkdir(parents=True)

    def write(name: str, subset: list[dict], folder: str) -> None:
        with open(root / name, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["file", "lat", "lon"])
            for r in subset:
                shutil.copy(demo_data / "images" / r["file"], root / folder / r["file"])
                w.writerow([f"{folder}/{r['file']}", r["lat"], r["lon"]])

    write("database.csv", rows[:8], "database")
    write("queries.csv", rows[:2], "queries")  # two of the references: found at rank 1
    proc = _run("--data", str(root), "--variants", "vlad_rootsift_fast:n_words=16")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    table = [ln for ln in lines if ln.startswith("|")]
    assert len(table) == 3 and all(ln.count("|") == 10 for ln in table)
    assert table[0].startswith("| descriptor | options | R@1 full")
    cells = [c.strip() for c in table[2].strip("|").split("|")]
    assert cells[:2] == ["vlad_rootsift_fast", "n_words=16"]
    assert cells[2:6] == ["2/2"] * 4
    assert all(float(c) > 0 for c in cells[6:])
    assert any(ln.startswith("# SF night: 2 queries") for ln in lines)
