"""benchmarks/bench_scale.py end to end on a tiny map: the script keeps working (builds in a
child, fresh-process queries, the side-by-side table) and its recall column agrees with exact
search (flat is exact by construction; pq must be close)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from repo_scripts import load

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
    policy = out.stdout.split("pq: thread policy and re-rank")[-1].split("\n\n")[0].splitlines()
    for shape in ("search", "paper", "posterior"):  # every variant of every shape timed
        times = [float(line.split()[-3]) for line in policy if line.startswith(f"  {shape} ")]
        assert len(times) == 3 and all(t > 0 for t in times), policy
    host = out.stdout.split("host speed: the 1-submap")[-1].split("\n\n")[0].splitlines()[1:]
    assert [line.split(":")[0].strip() for line in host] == [
        "pq, 1 submap", "pq, largest submap", "flat, 1 submap", "flat, largest submap"], host
    assert any("= 1.00x the table's fastest" in line for line in host), host
    res = json.loads((tmp_path / "n6000" / "results.json").read_text())
    assert set(res) == {"pq", "flat"}
    assert res["flat"]["recall1"] >= 0.95 and res["flat"]["recall50"] >= 0.99  # exact index
    assert res["pq"]["recall1"] >= 0.95 and res["pq"]["recall50"] >= 0.95
    for r in res.values():
        assert 0 < r["build_rss"] < 4 and r["start_s"] > 0 and r["n_submaps"] == 4
        assert r["rss_start"]["RssAnon"] > 0 and len(r["lat_global"]) == 3
        for split in r["host"].values():  # 300 paired queries, a median on either side or all
            assert split["probe_p5"] > 0 and 0 < split["share_full"] <= 1
            assert split["all"] > 0 and split["full"] > 0


def test_host_speed_splits_runs_by_the_probe_next_to_them():
    """Known split: 30 runs of 1 ms next to 0.10 ms probes, 70 of 2 ms next to 0.16 ms ones
    (1.6x slower: beyond FULL_SPEED of the 5th percentile)."""
    cpuinfo = load("benchmarks/cpuinfo.py")
    ms, probes = [1.0] * 30 + [2.0] * 70, [0.10] * 30 + [0.16] * 70
    split = cpuinfo.by_host_speed(ms, probes)
    assert split == {"all": 2.0, "full": 1.0, "contended": 2.0, "share_full": 0.3,
                     "probe_p5": 0.10, "probe_median": 0.16}
    assert math.isnan(cpuinfo.by_host_speed([1.0], [0.1])["contended"])  # all at full speed
    assert all(math.isnan(v) for v in cpuinfo.by_host_speed([], []).values())
    row = cpuinfo.host_speed_row("x", split, 0.05)
    assert row.startswith("x: 2.00 ms; host at full speed 1.00 ms (30% of runs), contended 2.00")
    assert "= 2.00x the table's fastest" in row


def test_paired_times_each_run_between_two_probes(monkeypatch):
    cpuinfo = load("benchmarks/cpuinfo.py")
    probes = iter([0.1, 0.3, 0.5, 0.7, 0.9])  # before run 0, after runs 0..3
    monkeypatch.setattr(cpuinfo, "probe_ms", lambda: next(probes))
    seen: list[int] = []
    ms, around = cpuinfo.paired(seen.append, 2, warm=2)
    assert seen == [0, 1, 2, 3] and len(ms) == 2 and all(m >= 0 for m in ms)
    assert around == pytest.approx([0.6, 0.8])  # the warm-up runs' probes left out
