"""The CLI contract: build-map → localize → evaluate (--json), as subprocesses like a user."""

import csv
import json
import subprocess
import sys

import pytest

from vlm_vpr_ros.geodesy import haversine_km

VLM_VPR = [sys.executable, "-m", "vlm_vpr_ros.cli"]


def run(*args, check=True):
    proc = subprocess.run([*VLM_VPR, *map(str, args)], capture_output=True, text=True,
                          timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


@pytest.fixture(scope="module")
def queries(tmp_path_factory, demo_data):
    """10 altered demo queries (not pixel copies) with ground truth."""
    import cv2
    import numpy as np

    from vlm_vpr_ros.evaluation.demo import make_query
    from vlm_vpr_ros.files.images import load_image

    d = tmp_path_factory.mktemp("q")
    rows = list(csv.DictReader(open(demo_data / "coords.csv")))[:10]
    for i, r in enumerate(rows):
        q = make_query(load_image(demo_data / "images" / r["file"]), np.random.default_rng(i))
        cv2.imwrite(str(d / r["file"]), cv2.cvtColor(q, cv2.COLOR_RGB2BGR))
    (d / "broken.jpg").write_bytes(b"\xff\xd8garbage")
    with open(d / "queries.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "lat", "lon"])
        for r in rows:
            w.writerow([r["file"], r["lat"], r["lon"]])
        w.writerow(["broken.jpg", 0, 0])
    return d


def test_help_lists_commands():
    out = run("--help").stdout
    for cmd in ("build-map", "localize", "evaluate", "demo", "descriptors"):
        assert cmd in out


def test_build_localize_evaluate(tmp_path, demo_data, queries):
    m = tmp_path / "map"
    out = run("build-map", "--images", demo_data / "images", "--coords",
              demo_data / "coords.csv", "--out", m, "--descriptor", "vlad_rootsift_fast",
              "--partition", "country").stdout
    assert "71 references" in out
    res = tmp_path / "res.csv"
    run("localize", "--map", m, "--images", queries, "--queries", queries / "queries.csv",
        "--priors", demo_data / "priors_osv5m_baseline.csv", "--top-p", "10", "--out", res)
    rows = list(csv.DictReader(open(res)))
    assert len(rows) == 11
    for col in ("file", "lat", "lon", "prior_lat", "prior_lon", "prior_source", "submap",
                "ref_id", "uncertainty_m", "flags"):
        assert col in rows[0]
    broken = [r for r in rows if r["file"] == "broken.jpg"][0]
    assert broken["lat"] == "" and "image_error" in broken["flags"]
    ok = [r for r in rows if r["file"] != "broken.jpg"]
    assert all(r["prior_source"] == "recorded" and r["submap"] for r in ok)
    # evaluate --json: recompute the expected numbers independently from the CSVs
    proc = run("evaluate", "--results", res, "--ground-truth", queries / "queries.csv", "--json")
    summary = json.loads(proc.stdout)
    assert set(summary) == {"n", "accuracy", "median_km", "recall_pct", "fixes",
                            "coverage68_pct", "coverage95_pct", "integrity", "junk_rows",
                            "junk"}
    assert summary["n"] == 11 and summary["junk_rows"] == 0 and summary["junk"] == {}
    assert summary["integrity"]["fixes"] == summary["fixes"]["n"]  # tests/test_integrity_report
    gt = {r["file"]: (float(r["lat"]), float(r["lon"]))
          for r in csv.DictReader(open(queries / "queries.csv"))}
    errs = [haversine_km(float(r["lat"]), float(r["lon"]), *gt[r["file"]]) for r in ok]
    for key, t in (("1km", 1), ("25km", 25), ("200km", 200), ("750km", 750), ("2500km", 2500)):
        assert summary["accuracy"][key] == pytest.approx(
            round(100 * sum(e <= t for e in errs) / 11, 2))
    table = run("evaluate", "--results", res, "--ground-truth", queries / "queries.csv").stdout
    assert "2500km" in table and "coverage:" in table and "coverage:" not in proc.stdout
    assert "recall within 25 m: R@1" in table and "fixes (status fix):" in table


def test_localize_without_prior_flags_rows(tmp_path, demo_map, queries):
    res = tmp_path / "res.csv"
    run("localize", "--map", demo_map, "--images", queries, "--queries",
        queries / "queries.csv", "--out", res)
    rows = [r for r in csv.DictReader(open(res)) if r["file"] != "broken.jpg"]
    assert all("no_prior" in r["flags"] and r["submap"] == "*" for r in rows)
    # VPR alone finds the altered copies of these map images
    assert sum(r["ref_id"] == r["file"] for r in rows) >= 8


def test_errors_are_clear_exit_codes(tmp_path):
    (tmp_path / "q.csv").write_text("file\na.jpg\n")
    proc = run("localize", "--map", tmp_path / "nomap", "--images", tmp_path, "--queries",
               tmp_path / "q.csv", "--out", tmp_path / "r.csv", check=False)
    assert proc.returncode == 2 and "map folder not found" in proc.stderr
    proc = run("build-map", "--images", tmp_path, "--coords", tmp_path / "c.csv", "--out",
               tmp_path / "m", "--descriptor", "nope", check=False)
    assert proc.returncode == 2 and "not found" in proc.stderr  # c.csv is checked first
    (tmp_path / "c.csv").write_text("file,lat,lon\na.jpg,1,2\n")
    proc = run("build-map", "--images", tmp_path, "--coords", tmp_path / "c.csv", "--out",
               tmp_path / "m", "--descriptor", "nope", check=False)
    assert proc.returncode == 2 and "choices: " in proc.stderr and "vlad_rootsift" in proc.stderr
    proc = run("build-map", "--images", tmp_path, "--coords", tmp_path / "none.csv", "--out",
               tmp_path / "m", check=False)
    assert proc.returncode == 2 and "not found" in proc.stderr


def test_started_ahead_keeps_order_and_a_bounded_window():
    """The prior-request pump of localize (images and precomputed descriptors): items come back
    in order, each started before it is handed out, never more than ``window`` ahead of the
    one handed out."""
    from vlm_vpr_ros.localization.batch import started_ahead

    started, seen = [], []

    def start(x):
        started.append(x)
        return x * 10

    for item, handle in started_ahead(range(7), start, window=3):
        assert handle == item * 10 and item in started
        assert len(started) - (len(seen) + 1) <= 3  # at most 3 started ahead of this one
        seen.append(item)
    assert seen == started == list(range(7))
    assert [i for i, _ in started_ahead([], start)] == []
    assert [i for i, _ in started_ahead("ab", str.upper, window=0)] == ["a", "b"]
