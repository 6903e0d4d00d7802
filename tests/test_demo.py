"""The demo (one shared run, ``demo_run``): the look-alike step shows the prior's value (target:
prior + VPR beats VPR only by >= 20 points at 25 m), and its numbers hold against independent
references (brute-force nearest neighbours, distances recomputed, the priors scored directly);
the README's and docs' demo tables are what it produced, and docs/api.md's session runs as
written on its output. Every test of the demo's output is in this file: one worker runs the demo
and its tests (a second worker waiting on the shared run sat idle ~60 s of the suite)."""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from vlm_vpr_ros.evaluation.demo import (FUSED, PAPER, PRIOR, THRESHOLDS, TITLES, TRUSTED,
                                         VPR, DEMO_DATA)
from vlm_vpr_ros.geodesy import haversine_km

from repo_scripts import REPO, load


@pytest.fixture(scope="module")
def doc(demo_run):
    out, _ = demo_run
    return json.loads((out / "demo.json").read_text())


def test_lookalike_step_prior_fixes_what_vpr_gets_wrong(doc):
    look = doc["summaries"]["lookalike"]
    vpr, fused = look[VPR]["accuracy"]["0.025km"], look[FUSED]["accuracy"]["0.025km"]
    assert fused >= vpr + 20.0, (vpr, fused)  # the target
    assert 25.0 <= vpr <= 75.0  # a coin toss between a place and its look-alike
    assert look[FUSED]["accuracy"]["0.025km"] > look[PAPER]["accuracy"]["0.025km"]
    # on the plain map the place is unique: VPR alone and the default fusion get every query
    plain = doc["summaries"]["map"]
    assert plain[VPR]["accuracy"]["0.025km"] == plain[FUSED]["accuracy"]["0.025km"] == 100.0
    assert set(doc["tables"]) == {"map", "lookalike", "bag", "fixes"}
    assert doc["summaries"]["bag"]["bag, " + FUSED] == plain[FUSED]  # same frames, same answers


def test_every_fix_is_right_and_fixes_need_verification(demo_run, doc):
    """The fix columns, recomputed from the results CSVs (status column) and the ground truth
    (haversine): the default rows are verified; on the plain map nearly every answer is a fix,
    each at the query's own place; on the look-alike map none is a fix by default (a place and
    its look-alike give the same inliers), and the fixes a trusted prior allows are right."""
    from vlm_vpr_ros.files.csvio import read_table

    out, printed = demo_run
    truth = {r["file"]: (float(r["lat"]), float(r["lon"]))
             for r in read_table(out / "queries.csv", ("file", "lat", "lon"))}
    seen = {}
    for step, folder in (("map", out / "results"), ("lookalike", out / "lookalike" / "results")):
        for i, (name, summary) in enumerate(doc["summaries"][step].items()):
            if summary["fixes"] is None:  # not verified: the baselines and the prior alone
                assert name in (VPR, PRIOR) or name.startswith("paper"), name
                continue
            rows = read_table(folder / f"results_{i}.csv", ("file", "status"))
            errs = [float(haversine_km(float(r["lat"]), float(r["lon"]), *truth[r["file"]]))
                    for r in rows if r["status"] == "fix"]
            fx = summary["fixes"]
            assert fx["n"] == len(errs) and fx["rate_pct"] == round(100 * len(errs) / 71, 2)
            assert all(e <= 0.025 for e in errs), (step, name, errs)
            assert fx["precision25_pct"] == (100.0 if errs else None)
            seen[step, name] = len(errs)
    assert seen[("map", FUSED)] >= 64  # 90 %: the altered copies verify against their source
    # issue 27: leave-one-out leaves out every copy of the held-out photo, so the look-alike
    # map's protection residual is a place's size, not the 5,000 km to the photo's copy; a
    # trusted prior then gives fixes again (16 of 71 before the protection level, all right:
    # within 10 %), never by default
    assert seen[("lookalike", FUSED)] == 0 and 15 <= seen[("lookalike", TRUSTED)] <= 17
    look_map = out / "lookalike" / "map"
    name = json.loads((look_map / "manifest.json").read_text())["verification_calibration"]
    look = json.loads((look_map / name).read_text())
    assert look["protection"]["residual_m"] < 100.0
    assert doc["summaries"]["bag"]["bag, " + FUSED]["fixes"]["n"] == seen[("map", FUSED)]
    assert "fixes: the share of answers published as STATUS_FIX" in printed


def test_vpr_only_is_the_brute_force_nearest_neighbour(demo_run):
    """VPR only on the look-alike map = argmin of squared L2 over all 284 references."""
    from vlm_vpr_ros.files.csvio import read_table
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    out, _ = demo_run
    q = np.load(out / "queries_descriptors.npy")
    look = ReferenceMap.load(out / "lookalike" / "map")
    refs, ids = look.all_descriptors(), look.all_ids()
    d2 = ((q[:, None, :].astype(np.float64) - refs[None].astype(np.float64)) ** 2).sum(-1)
    rows = read_table(out / "lookalike" / "results" / "results_0.csv", ("ref_id",))
    assert [r["ref_id"] for r in rows] == [ids[i] for i in d2.argmin(1)]
    truth = read_table(out / "queries.csv", ("file", "lat", "lon"))
    # the place (or its second photo) vs its look-alike: the answers split between them
    at_place = [ids[i].startswith("place") for i in d2.argmin(1)]
    assert [ids[i].split("/", 1)[1] for i in d2.argmin(1)] == [t["file"] for t in truth]
    assert 0.25 <= np.mean(at_place) <= 0.75


def test_lookalike_map_geometry(demo_run):
    """Every place: two references within 25 m of it, two 5000 km away (haversine)."""
    from vlm_vpr_ros.files.csvio import read_table

    out, _ = demo_run
    truth = {r["file"]: (float(r["lat"]), float(r["lon"]))
             for r in read_table(out / "queries.csv", ("file", "lat", "lon"))}
    refs = read_table(out / "lookalike" / "refs.csv", ("file", "lat", "lon"))
    assert len(refs) == 4 * len(truth) == 284
    for r in refs:
        kind, f = r["file"].split("/", 1)
        km = float(haversine_km(float(r["lat"]), float(r["lon"]), *truth[f]))
        if kind.startswith("place"):
            assert km <= 0.025, r
        else:
            assert abs(km - 5000.0) < 1.0, r
        assert (out / "lookalike" / "refs" / r["file"]).is_file()


def test_prior_only_row_scores_the_priors_directly(doc):
    from vlm_vpr_ros.files.csvio import read_table
    from vlm_vpr_ros.geodesy import accuracy_table

    pri = {r["file"]: (float(r["lat"]), float(r["lon"]))
           for r in read_table(DEMO_DATA / "priors_osv5m_baseline.csv", ("file", "lat", "lon"))}
    gt = read_table(DEMO_DATA / "coords.csv", ("file", "lat", "lon"))
    errs = [float(haversine_km(*pri[r["file"]], float(r["lat"]), float(r["lon"]))) for r in gt]
    want = accuracy_table(errs, THRESHOLDS)
    for step in ("map", "lookalike"):
        got = doc["summaries"][step][PRIOR]
        assert got["accuracy"] == {k: round(v, 2) for k, v in want.items()}
        assert got["median_km"] == pytest.approx(float(np.median(errs)), abs=1e-3)


def test_printed_tables_are_the_json_tables(demo_run, doc):
    """What the demo prints is what the docs show: both come from metrics.table_cells."""
    from vlm_vpr_ros.evaluation.metrics import format_table, table_cells

    _, printed = demo_run
    for step, rows in doc["summaries"].items():
        assert format_table(rows, title=TITLES[step]) in printed
        head, body = table_cells(rows)
        assert doc["tables"][step] == {"title": TITLES[step], "columns": head, "rows": body}
        assert head[2] == "25m"
    assert "built from the shipped images" in printed  # the look-alikes are stated as such
    # the twins are exact ties (same image, same descriptor) for every query, said as such
    assert "for 71 of 71 queries\n      the best match's twin is at the bit-identical" in printed
    assert "[1/5]" in printed and " s CPU; tables in " in printed  # steps and the time it took
    from vlm_vpr_ros.evaluation.demo import fixes_table
    from vlm_vpr_ros.evaluation.metrics import format_cells

    head, body = fixes_table(doc["summaries"])  # the verified rows of every step
    assert doc["tables"]["fixes"] == {"columns": head, "rows": body}
    assert format_cells(head, body, TITLES["fixes"]) in printed
    assert [r[0] for r in body] == [f"demo map: {FUSED}", f"look-alike map: {FUSED}",
                                    f"look-alike map: {TRUSTED}"]


def test_figures_are_images(doc):
    for key in ("lookalike_error_cdf_png", "lookalike_contact_sheet_png", "world_map_png"):
        img = cv2.imread(doc["figures"][key], cv2.IMREAD_COLOR)
        assert img is not None and img.shape[0] > 300 and img.shape[1] > 500, key


def code_blocks(path: Path) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", path.read_text(encoding="utf-8"), re.S | re.M)


def test_api_page_runs(demo_run, tmp_path, monkeypatch):
    from vlm_vpr_ros import Hypothesis
    from vlm_vpr_ros.files.csvio import read_table

    out, _ = demo_run
    (tmp_path / "demo_out").symlink_to(out)  # "from the repository folder, after make demo"
    (tmp_path / "vlm_vpr_ros").symlink_to(REPO / "vlm_vpr_ros")
    monkeypatch.chdir(tmp_path)
    blocks = code_blocks(REPO / "docs" / "api.md")
    assert len(blocks) >= 4
    ns: dict = {}
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        for code in blocks:
            exec(compile(code, "docs/api.md", "exec"), ns)  # noqa: S102 - the doc's own code
    truth = {r["file"]: (float(r["lat"]), float(r["lon"]))
             for r in read_table(out / "queries.csv", ("file", "lat", "lon"))}
    hyp = ns["hyp"]
    assert isinstance(hyp, Hypothesis) and hyp.fusion == "posterior"
    assert haversine_km(hyp.lat, hyp.lon, *truth["546314506564628.jpg"]) < 0.025
    assert ns["answer"].ok and ns["answer"].source == "recorded"
    assert "MapError" in printed.getvalue()  # the error example
    assert printed.getvalue().count("\n") >= 8


def test_docs_tables_equal_the_shipped_demo(demo_run):
    """The README's and docs' demo tables are exactly what `make demo` produces."""
    out, _ = demo_run
    gen_docs = load("scripts/gen_docs.py")
    diffs, _ = gen_docs.run(REPO, check=True, overrides={"demo": str(out / "demo.json")},
                            only={"demo"}, strict=True)
    assert not diffs, ("tables differ from the demo; run `make demo && python "
                       "scripts/gen_docs.py`:\n" + "\n".join(diffs))
