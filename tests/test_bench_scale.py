"""benchmarks/bench_scale.py end to end on a tiny map: the script keeps working (builds in a
child, fresh-process queries, the side-by-side table) and its recall column agrees with exact
search (flat is exact by construction; pq must be close)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_bench_scale_small_run_prints_the_table(tmp_path):
    cmd = [sys.executable, str(REPO / "benchmarks" / "bench_scale.py"), "--n", "6000",
           "--kinds", "pq,flat", "--clusters", "4", "--queries", "40", "--global-queries", "3",
           "--recall-queries", "20", "--workdir", str(tmp_path), "--keep"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    for row in ("build peak RSS (GiB)", "fresh-process start (s)", "global (ms med/p95)",
                "largest submap, search only (ms med/p95)", "recall@50 vs exact (%)",
                "pq / flat (same run)"):
        assert row in out.stdout, out.stdout
    policy = out.stdout.split("pq: thread policy and re-rank")[1].split("\n\n")[0].splitlines()
    for shape in ("search", "paper", "posterior"):  # every variant of every shape timed
        times = [float(line.split()[-3]) for line in policy if line.startswith(f"  {shape} ")]
        assert len(times) == 3 and all(t > 0 for t in times), policy
    res = json.loads((tmp_path / "n6000" / "results.json").read_text())
    assert set(res) == {"pq", "flat"}
    assert res["flat"]["recall1"] >= 0.95 and res["flat"]["recall50"] >= 0.99  # exact index
    assert res["pq"]["recall1"] >= 0.95 and res["pq"]["recall50"] >= 0.95
    for r in res.values():
        assert 0 < r["build_rss"] < 4 and r["start_s"] > 0 and r["n_submaps"] == 4
        assert r["rss_start"]["RssAnon"] > 0 and len(r["lat_global"]) == 3
