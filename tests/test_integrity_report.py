"""The integrity report (vlm_vpr_ros/evaluation/integrity.py): DO-229 regions, accuracy,
availability, HMI per fix and per scene, TTFF and gaps, against hand-made cases counted by brute
force; the Stanford diagram PNG; results CSVs with and without ``protection_m`` and with junk."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import cv2
import pytest

from vlm_vpr_ros.evaluation import integrity, integrity_tables
from vlm_vpr_ros.evaluation.integrity import Trial, integrity_report, time_series
from vlm_vpr_ros.errors import ConfigError, DataError

from repo_scripts import load

#: metres per degree of latitude on the package's sphere (haversine, R = 6371.0088 km)
M_PER_DEG = 6371008.8 * math.pi / 180.0
BASE = (37.7749, -122.4194)


def north(p: tuple[float, float], metres: float) -> tuple[float, float]:
    return (p[0] + metres / M_PER_DEG, p[1])


def place(k: int) -> tuple[float, float]:
    """Truth positions 1 km apart (distinct 25 m cells)."""
    return north(BASE, 1000.0 * k)


#: (error m, PL m or None, status, expected region by hand with AL = 50 m)
CASES = [
    (3.0, 10.0, "fix", "nominal"),
    (9.5, 10.0, "fix", "nominal"),
    (12.0, 30.0, "fix", "nominal"),
    (20.0, 10.0, "fix", "misleading"),
    (45.0, 40.0, "fix", "misleading"),
    (60.0, 40.0, "fix", "hazardously_misleading"),
    (300.0, 5.0, "fix", "hazardously_misleading"),
    (10.0, 50.0, "fix", "unavailable"),  # PL == AL: not available
    (80.0, 70.0, "fix", "unavailable"),  # a fix beyond the alert limit: unavailable, error > PL
    (5.0, 10.0, "no_fix", "unavailable"),
    (500.0, 5.0, "no_fix", "unavailable"),  # a wrong NO_FIX is no integrity failure
    (7.0, None, "fix", "no_pl"),
    (70.0, None, "fix", "no_pl"),
]


def trials_of(cases, keys=None) -> list[Trial]:
    out = []
    for i, (e, pl, st, _) in enumerate(cases):
        truth = place(i)
        out.append(Trial(truth, north(truth, e), st, pl, None,
                         keys[i] if keys else f"q{i}.jpg"))
    return out


def test_regions_and_counts_against_brute_force():
    trials = trials_of(CASES)
    for t, (e, *_rest, want) in zip(trials, CASES):
        assert t.error_m == pytest.approx(e, abs=1e-3)
        assert integrity.region(t, 50.0) == want
    rep = integrity_report(trials, 50.0)
    for name in (*integrity.REGIONS, "no_pl"):
        assert rep["regions"][name] == sum(c[3] == name for c in CASES), name
    fixes = [c for c in CASES if c[2] == "fix"]
    assert rep["fixes"] == len(fixes) == 11
    assert rep["availability_pct"] == pytest.approx(100.0 * 11 / 13, abs=0.01)
    # DO-229 HMI: available (PL < AL) and error > AL
    hmi = [c for c in fixes if c[1] is not None and c[1] < 50 and c[0] > 50]
    assert rep["hmi"]["count"] == len(hmi) == 2
    assert rep["hmi"]["per_fix"] == pytest.approx(2 / 11, abs=1e-6)
    # issue 27's HMI: FIX with error > PL, any PL (the unavailable 80 m / 70 m fix included)
    gt_pl = [c for c in fixes if c[1] is not None and c[0] > c[1]]
    assert rep["error_gt_pl"]["count"] == len(gt_pl) == 5
    gt_al = [c for c in fixes if c[0] > 50]  # a fix without PL still counts here
    assert rep["error_gt_al"]["count"] == len(gt_al) == 4
    # accuracy of fixes, nearest rank: sorted errors of the 11 fixes
    errs = sorted(c[0] for c in fixes)
    assert rep["accuracy_m"]["p50"] == pytest.approx(errs[math.ceil(0.5 * 11) - 1], abs=0.1)
    assert rep["accuracy_m"]["p95"] == pytest.approx(errs[math.ceil(0.95 * 11) - 1], abs=0.1)
    assert rep["accuracy_m"]["max"] == pytest.approx(300.0, abs=0.1)
    pls = sorted(c[1] for c in fixes if c[1] is not None)
    assert rep["protection_level"]["median_m"] == pls[math.ceil(0.5 * len(pls)) - 1]
    assert rep["fixes_pl_at_or_above_al"] == sum(c[2] == "fix" and c[1] is not None
                                                 and c[1] >= 50 for c in CASES) == 2
    assert rep["scenes"]["source"] == "key" and rep["scenes"]["n"] == 13
    assert rep["time"] is None
    # the printed table names the regions and both HMI counts
    text = integrity_tables.format_report(rep)
    assert "3 / 2 / 2 / 4" in text and "HMI (DO-229" in text and "issue 27" in text


def test_alert_limit_moves_the_regions():
    trials = trials_of(CASES)
    rep = integrity_report(trials, 100.0)
    # with AL 100 m: 60/40 becomes MI, 80/70 becomes MI, 10/50 nominal (PL 50 < 100)
    assert rep["regions"]["hazardously_misleading"] == 1
    assert rep["regions"]["misleading"] == 4
    assert rep["regions"]["nominal"] == 4
    for bad in (0, -1, "nan", "abc", float("inf"), True):
        with pytest.raises(ConfigError):
            integrity_report(trials, bad)


def test_repeated_frames_are_one_scene():
    """100 answers: 99 nominal repeats of one good scene, 1 HMI elsewhere; per fix the HMI
    rate looks small, per scene it is half the scenes: repetition cannot pass the test."""
    good, bad = place(0), place(5)
    trials = [Trial(good, north(good, 3.0), "fix", 10.0, None, "good.jpg") for _ in range(99)]
    trials.append(Trial(bad, north(bad, 80.0), "fix", 20.0, None, "bad.jpg"))
    rep = integrity_report(trials)
    assert rep["hmi"]["count"] == 1 and rep["hmi"]["per_fix"] == pytest.approx(0.01)
    sc = rep["scenes"]
    assert (sc["n"], sc["with_fix"], sc["hmi"]["count"]) == (2, 2, 1)
    assert sc["hmi"]["per_scene_with_fix"] == pytest.approx(0.5)
    # ten repeats of one HMI scene are ten HMI fixes but one HMI scene
    rep = integrity_report([Trial(bad, north(bad, 80.0), "fix", 20.0, None, "x")] * 10)
    assert rep["hmi"]["count"] == 10 and rep["scenes"]["hmi"]["count"] == 1


def test_scene_cells_when_keys_are_stamps():
    """Bag keys that are only stamps name no scene: truths snapped to 25 m cells instead."""
    a, b = place(0), place(1)
    stamps = [f"{1700000000 + i}.{i:09d}" for i in range(6)]
    trials = [Trial(north(a, d), north(a, 70.0), "fix", 10.0, float(i), stamps[i])
              for i, d in enumerate((0.0, 0.5, 1.0))]
    trials += [Trial(north(b, 0.2 * i), north(b, 2.0), "fix", 10.0, 3.0 + i, stamps[3 + i])
               for i in range(3)]
    src, cell = integrity.scene_of(trials[0])
    assert src == "cell25m" and integrity.scene_of(trials[1])[1] == cell
    assert integrity.scene_of(trials[3])[1] != cell
    rep = integrity_report(trials)
    assert rep["scenes"]["source"] == "cell25m"
    assert (rep["scenes"]["n"], rep["scenes"]["hmi"]["count"], rep["hmi"]["count"]) == (2, 1, 3)
    # an image name is the scene, whatever the truth says
    assert integrity.scene_of(Trial(a, a, "fix", key="dir/q1.jpg")) == ("key", "q1.jpg")


def test_ttff_and_gaps_on_a_time_series():
    p = place(0)
    fix_at = {3.0, 4.0, 8.0}
    trials = [Trial(p, p, "fix" if t in fix_at else "no_fix", 5.0, t)
              for t in (float(x) for x in range(10))]  # 0 .. 9 s
    ts = time_series(trials)
    times = sorted(fix_at)
    assert ts["ttff_s"] == times[0] - 0.0 == 3.0
    assert ts["longest_gap_s"] == max(b - a for a, b in zip(times, times[1:])) == 4.0
    assert ts["longest_outage_s"] == 4.0 and ts["span_s"] == 9.0
    # a long tail without fixes counts as an outage, not as a gap between fixes
    tail = [Trial(p, p, "fix" if t < 2 else "no_fix", 5.0, float(t)) for t in range(11)]
    ts = time_series(tail)
    assert (ts["ttff_s"], ts["longest_gap_s"], ts["longest_outage_s"]) == (0.0, 1.0, 9.0)
    # explicit start (node started before the first answer) and no fix at all
    assert time_series(trials, t_start=-2.0)["ttff_s"] == 5.0
    none = time_series([Trial(p, p, "no_fix", 5.0, float(t)) for t in range(3)])
    assert none["ttff_s"] is None and none["longest_gap_s"] is None
    assert none["longest_outage_s"] == 2.0
    assert integrity_report(trials)["time"]["ttff_s"] == 3.0


def test_png_and_json_written(tmp_path):
    trials = trials_of(CASES)
    rep = integrity_report(trials)
    out = tmp_path / "res_integrity"
    paths = integrity.write_report(out, rep, trials, "hand-made")
    img = cv2.imread(paths["stanford_png"])
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 300
    doc = json.loads(Path(paths["integrity_json"]).read_text())
    assert doc["regions"] == rep["regions"] and doc["outputs"] == paths
    # an earlier report is kept without overwrite, replaced with it
    with pytest.raises(OSError, match="overwrite"):
        integrity.write_report(out, rep, trials)
    integrity.write_report(out, integrity_report(trials, 100.0), trials, overwrite=True)
    assert json.loads((out / "integrity.json").read_text())["alert_limit_m"] == 100.0
    # a folder the tool did not write is never replaced
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    with pytest.raises(OSError):
        integrity.write_report(mine, rep, trials, overwrite=True)
    assert (mine / "notes.txt").read_text() == "keep"


def _write(path: Path, cols: list[str], rows: list[list]) -> Path:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        w.writerows(rows)
    return path


def _files(tmp_path: Path, with_pl: bool, pls=None) -> tuple[Path, Path]:
    gt_rows, res_rows = [], []
    for i, (e, pl, st, _) in enumerate(CASES):
        truth = place(i)
        est = north(truth, e)
        gt_rows.append([f"q{i}.jpg", truth[0], truth[1]])
        row = [f"imgs/q{i}.jpg", f"{est[0]:.7f}", f"{est[1]:.7f}", st, "0.99"]
        if with_pl:
            row.append("" if pl is None else (pls[i] if pls else pl))
        res_rows.append(row)
    res_rows.append(["unknown.jpg", "1", "2", "fix", "1"])  # no ground truth: skipped
    gt = _write(tmp_path / "gt.csv", ["file", "lat", "lon"], gt_rows)
    cols = ["file", "lat", "lon", "status", "p_correct"] + (["protection_m"] if with_pl else [])
    return _write(tmp_path / "results.csv", cols, res_rows), gt


def test_cli_evaluate_with_protection_level(tmp_path, capsys):
    from vlm_vpr_ros.cli import main

    res, gt = _files(tmp_path, True)
    assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)["integrity"]
    assert doc["regions"] == integrity_report(trials_of(CASES))["regions"]
    assert doc["protection_level"]["available"] and doc["scenes"]["n"] == 13
    assert Path(doc["outputs"]["stanford_png"]).is_file()
    assert Path(doc["outputs"]["integrity_json"]).parent == tmp_path / "results_integrity"
    # a second run keeps the first folder (a warning) and still prints the table
    assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt)]) == 0
    out = capsys.readouterr().out
    assert "nominal / MI / HMI / unavailable" in out and "stanford_png" not in out
    assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt),
                 "--alert-limit-m", "100", "--overwrite"]) == 0
    doc = json.loads((tmp_path / "results_integrity" / "integrity.json").read_text())
    assert doc["alert_limit_m"] == 100.0
    for bad in ("0", "-5", "nan", "abc"):
        assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt),
                     "--alert-limit-m", bad]) == 2


def test_results_without_protection_column(tmp_path, capsys):
    from vlm_vpr_ros.cli import main

    res, gt = _files(tmp_path, False)
    assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt)]) == 0
    out = capsys.readouterr().out
    assert "protection level" in out and "not available" in out
    rep = integrity.evaluate_integrity(res, gt)
    assert rep["protection_level"]["available"] is False
    fixes = [c for c in CASES if c[2] == "fix"]
    # every fix is "no PL"; fixes > 50 m off still counted
    assert rep["regions"]["no_pl"] == len(fixes)
    assert rep["error_gt_al"]["count"] == sum(c[0] > 50 for c in fixes)
    assert rep["hmi"]["count"] == 0 and rep["error_gt_pl"]["count"] == 0
    assert "no protection_m column" in integrity_tables.format_report(rep)
    # a column with no usable value (an evaluate-bag frames.csv of today's node): the same
    res, gt = _files(tmp_path, True, {i: "" if i % 2 else "nan" for i in range(13)})
    empty = integrity.evaluate_integrity(res, gt)
    assert empty["protection_level"]["available"] is False
    n_junk = sum(c[1] is not None and i % 2 == 0 for i, c in enumerate(CASES))  # the "nan"s
    assert empty["protection_level"]["invalid_values"] == n_junk == 6
    assert empty["regions"] == rep["regions"] and "6 junk" in integrity_tables.format_report(empty)


def test_junk_protection_levels(tmp_path):
    junk = {0: "nan", 1: "NaN", 2: "abc", 3: "-4", 4: "inf", 5: "1e999", 6: "3_0"}
    pls = {i: junk.get(i, c[1]) for i, c in enumerate(CASES)}
    res, gt = _files(tmp_path, True, pls)
    rep = integrity.evaluate_integrity(res, gt)
    assert rep["protection_level"]["invalid_values"] == len(junk)
    # the seven junk PLs (all fixes) join the two fixes without PL
    assert rep["regions"]["no_pl"] == len(junk) + 2
    assert rep["regions"]["nominal"] == 0 and rep["fixes"] == 11
    for v in junk.values():
        assert integrity.protection_value(v) is None
    assert integrity.protection_value(" 12.5 ") == 12.5 and integrity.protection_value("0") == 0


def test_junk_rows_and_bad_files(tmp_path):
    res, gt = _files(tmp_path, True)
    text = res.read_text().splitlines()
    text[1] = "q0.jpg"  # a short row: missing cells read as empty
    text[2] += ",extra,cells"
    text.append("q3.jpg,not-a-lat,x,fix,1,5")  # a fix without a position: no error, no crash
    res.write_text("\n".join(text) + "\n")
    trials, info = integrity.read_trials(res, {f"q{i}.jpg": place(i) for i in range(13)})
    assert info["rows"] == len(text) - 1 and info["missing_truth"] == 1
    assert trials[0].est is None and trials[0].status == ""
    assert integrity_report(trials)["scored"] == len(trials) - 2
    nul = tmp_path / "nul.csv"  # a NUL byte in a cell: a junk value, that row has no estimate
    nul.write_bytes(b"file,lat,lon,status\nq0.jpg,1,\x002,fix\n")
    (t,), _ = integrity.read_trials(nul, {"q0.jpg": place(0)})
    assert t.est is None and t.error_m is None
    latin = tmp_path / "latin1.csv"
    latin.write_bytes(b"file,lat,lon\nq\xe9.jpg,1,2\n")
    with pytest.raises(DataError, match="latin1.csv:2: malformed CSV"):
        integrity.read_trials(latin, {})
    with pytest.raises(DataError, match="not found"):
        integrity.read_trials(tmp_path / "missing.csv", {})


def test_evaluate_bag_writes_the_report(demo_map, demo_data, tmp_path):
    """evaluate-bag: the report in summary.json, integrity.json and stanford.png in the final
    folder; counts and TTFF equal a brute-force recount of frames.csv."""
    from vlm_vpr_ros.bags.evaluate import BagEvalConfig, evaluate_bag
    from vlm_vpr_ros.bags.make import make_bag
    from vlm_vpr_ros.bags.reader import open_bag
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.priors import create_prior_provider

    lines = (demo_data / "coords.csv").read_text().splitlines()
    queries = tmp_path / "q.csv"
    queries.write_text("\n".join(lines[:5]) + "\n")
    make_bag(demo_data / "images", queries, tmp_path / "bag", rate_hz=2.0,
             start_time_ns=1_700_000_000_000_000_000, progress=False)
    provider = create_prior_provider("none")
    res = evaluate_bag(open_bag(tmp_path / "bag"), LocalizationPipeline.open(demo_map),
                       provider, tmp_path / "ev", BagEvalConfig(alert_limit_m=40.0),
                       progress=False)
    rep = res["integrity"]
    with (tmp_path / "ev" / "frames.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert "protection_m" in rows[0]
    stamps = [int(r["stamp_ns"]) / 1e9 for r in rows]
    fix_t = [s for s, r in zip(stamps, rows) if r["status"] == "fix"]
    assert rep["alert_limit_m"] == 40.0 and rep["answers"] == len(rows) == 4
    assert rep["fixes"] == len(fix_t)
    assert rep["time"]["span_s"] == pytest.approx(max(stamps) - min(stamps), abs=1e-3)
    assert rep["time"]["ttff_s"] == (None if not fix_t else
                                     pytest.approx(fix_t[0] - min(stamps), abs=1e-3))
    assert rep["scenes"]["source"] == "key" and rep["scenes"]["n"] == 4
    out = res["details"]["outputs"]
    assert Path(out["stanford_png"]) == tmp_path / "ev" / "stanford.png"
    assert cv2.imread(out["stanford_png"]) is not None
    doc = json.loads(Path(out["integrity_json"]).read_text())
    assert doc["outputs"]["stanford_png"] == out["stanford_png"]
    summary = json.loads((tmp_path / "ev" / "summary.json").read_text())
    assert summary["integrity"]["regions"] == rep["regions"]


def test_soak_protection_level_from_covariance_and_frames():
    """The soak's assumed relation PL = k σ: a circular 2-D Gaussian leaves PL with probability
    1e-3 (Monte Carlo); junk covariances give None; frames fit inside 640x480."""
    import numpy as np

    soak = load("benchmarks/soak_node.py")
    sigma = 10.0
    pl = soak.protection_from_covariance([sigma ** 2, 0, 0, 0, 4.0, 0, 0, 0, 1e6])
    r = np.hypot(*np.random.default_rng(0).normal(0.0, sigma, (2, 2_000_000)))
    assert np.mean(r > pl) == pytest.approx(1e-3, rel=0.1)
    for bad in (None, [], [float("nan")] * 9, [-1.0] * 9, ["x"] * 9):
        assert soak.protection_from_covariance(bad) is None
    assert soak.fit_inside(np.zeros((1024, 679, 3), np.uint8)).shape == (480, 318, 3)
    assert soak.fit_inside(np.zeros((679, 1024, 3), np.uint8)).shape == (424, 640, 3)
    assert soak.fit_inside(np.zeros((100, 50, 3), np.uint8)).shape == (100, 50, 3)
    trace = [(0.0, 100.0), (10.0, 200.0), (120.0, 220.0), (300.0, 230.0), (310.0, 240.0),
             (320.0, 250.0)]
    rss = soak.rss_summary(trace)
    assert rss["baseline_mib"] == 210.0 and rss["end_mib"] == 240.0
    assert rss["change_pct"] == pytest.approx(100 * 30 / 210, abs=0.01)
