"""Issue 43, found elsewhere: the localizer's own guard uses the one sigma rule; ``localize``
checks every input and option before opening the map; no output of a command (``--out``,
``--save-matches``, ``--integrity-out``, ``evaluate-bag --out``, ``build-map --out``) is one of
its inputs or a folder holding one."""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from vlm_vpr_ros.cli import main
from vlm_vpr_ros.localization.localizer import Localizer
from vlm_vpr_ros.mapping.assemble import assemble_map
from vlm_vpr_ros.priors.provider import (MAX_PRIOR_SIGMA_KM, MIN_PRIOR_SIGMA_KM, Prior,
                                         PriorResult)


def _sha(*paths: Path) -> dict[str, bytes]:
    out = {}
    for root in paths:
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        out.update({str(p): p.read_bytes() for p in files})
    return out


# -- 1. the localizer's guard: the one sigma rule -------------------------------------------------
@pytest.fixture(scope="module")
def two_towns():
    rng = np.random.default_rng(3)
    towns = [(40.0, -3.7), (48.9, 2.35), (52.5, 13.4)]
    coords = np.array([(la + rng.normal(0, 0.01), lo + rng.normal(0, 0.01))
                       for la, lo in towns for _ in range(15)])
    ids = [f"{'abc'[t]}_{i:02d}" for t in range(3) for i in range(15)]
    desc = rng.normal(size=(len(ids), 16)).astype(np.float32)
    ident = {"name": "synthetic", "dim": 16, "config": {}, "preprocessing": {}}
    return assemble_map(desc, coords, ids, ident, {}, "kmeans", 3), desc, ids


@pytest.mark.parametrize("sigma_km", [1e-300, MIN_PRIOR_SIGMA_KM / 2, 0.0, -1.0, 3e4, 1e12,
                                      math.inf, math.nan, "12 km"])
def test_a_sigma_outside_the_rule_is_an_invalid_prior(two_towns, sigma_km, caplog):
    """Before: any sigma > 0 passed; 1e-300 and 3e4 km then failed in the error model (an error
    on every query). Now: flagged ``prior_invalid``, the answer of no prior."""
    m, desc, ids = two_towns
    loc = Localizer(m)
    q = desc[ids.index("b_03")]
    ref = loc.localize(q, None)
    hyp = loc.localize(q, PriorResult(Prior(48.9, 2.35, "mine", sigma_km), "mine"))
    assert {"prior_failed", "prior_invalid", "no_prior"} <= set(hyp.flags) and hyp.flagged
    assert hyp.prior is None and hyp.ref_id == ref.ref_id == "b_03"
    assert math.isfinite(hyp.uncertainty_m) and hyp.uncertainty_m <= hyp.radius95_m
    assert any("ignoring an invalid prior" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("sigma_km", [MIN_PRIOR_SIGMA_KM, 0.05, 2500.0, MAX_PRIOR_SIGMA_KM])
def test_a_sigma_inside_the_rule_is_used(two_towns, sigma_km):
    m, desc, ids = two_towns
    hyp = Localizer(m).localize(desc[ids.index("b_03")],
                                PriorResult(Prior(48.9, 2.35, "mine", sigma_km), "mine"))
    assert "prior_invalid" not in hyp.flags and "no_prior" not in hyp.flags
    assert hyp.prior is not None and hyp.ref_id.startswith("b_")  # the prior's town


# -- 2a. every check before the map is opened ----------------------------------------------------
@pytest.fixture
def queries(demo_data, tmp_path) -> Path:
    names = sorted(p.name for p in (demo_data / "images").iterdir())[:3]
    q = tmp_path / "q.csv"
    q.write_text("file\n" + "\n".join(names) + "\n")
    return q


def _localize(demo_map, demo_data, queries, out, *extra) -> int:
    return main(["localize", "--map", str(demo_map), "--images", str(demo_data / "images"),
                 "--queries", str(queries), "--out", str(out), *map(str, extra)])


def test_bad_priors_and_options_refused_before_the_map(demo_map, demo_data, queries, tmp_path,
                                                       map_loads):
    names = queries.read_text().split()[1:]
    bad = tmp_path / "p.csv"
    bad.write_text(f"file,lat,lon,sigma_m\n{names[0]},37.7,-122.4,1e-300\n")
    out = tmp_path / "r.csv"
    cases = [("--priors", bad),
             ("--prior", "fixed", "--prior-option", "lat=1", "--prior-option", "lon=2",
              "--prior-option", "sigma_km=30000"),
             ("--prior", "fixed", "--prior-option", "colour=red"),
             ("--prior", "nope"),
             ("--priors", tmp_path / "missing.csv"),
             ("--fix-min-p-correct", "2"),
             ("--only-wrong",),
             ("--save-matches", tmp_path / "m", "--only-wrong"),
             ("--save-matches", tmp_path / "m", "--ground-truth", tmp_path / "missing.csv")]
    for extra in cases:
        assert _localize(demo_map, demo_data, queries, out, *extra) == 2, extra
        assert not map_loads, (extra, map_loads)
        assert not out.exists() and not out.with_name("r.csv.partial").exists()
    desc = tmp_path / "q.npy"
    np.save(desc, np.zeros((3, 70), np.float32))
    assert main(["localize", "--map", str(demo_map), "--query-descriptors", str(desc),
                 "--queries", str(queries), "--out", str(out), "--priors", str(bad)]) == 2
    assert not map_loads
    # a good prior still runs (the map is then opened once)
    good = tmp_path / "good.csv"
    good.write_text(f"file,lat,lon\n{names[0]},37.7,-122.4\n")
    assert _localize(demo_map, demo_data, queries, out, "--priors", good) == 0
    assert map_loads == [str(demo_map)] and out.is_file()


# -- 2b. --out is never an input -----------------------------------------------------------------
def test_out_is_never_an_input_even_a_results_csv(demo_map, demo_data, queries, tmp_path,
                                                  map_loads):
    out = tmp_path / "r.csv"
    assert _localize(demo_map, demo_data, queries, out) == 0
    map_loads.clear()
    gt = tmp_path / "gt.csv"
    shutil.copy(out, gt)  # results CSVs of ours, given as inputs
    pri = tmp_path / "pri.csv"
    shutil.copy(out, pri)
    os.link(out, tmp_path / "hard.csv")
    before = _sha(tmp_path)
    runs = [("--queries", out, "--out", out), ("--queries", out, "--out", tmp_path / "hard.csv"),
            ("--queries", queries, "--out", pri, "--priors", pri),
            ("--queries", queries, "--out", pri, "--prior", "recorded", "--prior-option",
             f"path={pri}"),
            ("--queries", queries, "--out", gt, "--save-matches", tmp_path / "m",
             "--ground-truth", gt)]
    for run in runs:
        for mode in ("--overwrite", "--resume"):
            rc = main(["localize", "--map", str(demo_map), "--images",
                       str(demo_data / "images"), *map(str, run), mode])
            assert rc == 2, (run, mode)
            assert _sha(tmp_path) == before and not map_loads
    # the unfinished file beside --out is never an input either
    q2 = tmp_path / "x.csv.partial"
    shutil.copy(queries, q2)
    before = _sha(tmp_path)
    assert main(["localize", "--map", str(demo_map), "--images", str(demo_data / "images"),
                 "--queries", str(q2), "--out", str(tmp_path / "x.csv"), "--overwrite"]) == 2
    assert _sha(tmp_path) == before and not map_loads


# -- 2c. --save-matches: never in an input folder, never over a user's file ---------------------
def test_save_matches_never_in_an_input_folder(demo_map, demo_data, queries, tmp_path, map_loads):
    from vlm_vpr_ros.evaluation.matches import sheet_names

    imgs = tmp_path / "imgs"
    shutil.copytree(demo_data / "images", imgs)
    files = queries.read_text().split()[1:]
    name = sheet_names(files)[files[0]]
    (imgs / name).write_bytes(b"a picture of mine")
    refs = tmp_path / "refs"
    refs.mkdir()
    before = _sha(tmp_path)
    out = tmp_path / "r.csv"
    for d in (imgs, imgs / "matches", refs, refs / "m", tmp_path):
        rc = main(["localize", "--map", str(demo_map), "--images", str(imgs), "--queries",
                   str(queries), "--out", str(out), "--save-matches", str(d),
                   "--reference-images", str(refs), "--overwrite"])
        assert rc == 2, d
        assert _sha(tmp_path) == before and not map_loads and not out.exists()
    # a user's folder holding a same-named file and other files: never replaced
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / name).write_bytes(b"mine too")
    (mine / "notes.txt").write_text("notes\n")
    before = _sha(mine)
    rc = main(["localize", "--map", str(demo_map), "--images", str(imgs), "--queries",
               str(queries), "--out", str(out), "--save-matches", str(mine), "--overwrite"])
    assert rc == 2 and _sha(mine) == before and not map_loads


def test_save_matches_overwrite_replaces_our_pictures(demo_map, demo_data, queries, tmp_path):
    from vlm_vpr_ros.evaluation.matches import sheet_names

    files = queries.read_text().split()[1:]
    d = tmp_path / "m"
    out = tmp_path / "r.csv"
    assert _localize(demo_map, demo_data, queries, out, "--save-matches", d) == 0
    drawn = {p.name: p.read_bytes() for p in d.iterdir()}
    assert set(drawn) == set(sheet_names(files).values())
    assert _localize(demo_map, demo_data, queries, tmp_path / "r2.csv", "--save-matches",
                     d) == 2
    (d / sheet_names(files)[files[0]]).write_bytes(b"stale")
    assert _localize(demo_map, demo_data, queries, out, "--save-matches", d,
                     "--overwrite") == 0
    assert {p.name: p.read_bytes() for p in d.iterdir()} == drawn


# -- the other commands: no output folder holds an input ----------------------------------------
def test_integrity_out_never_holds_an_input(tmp_path):
    res = tmp_path / "r.csv"
    res.write_text("file,lat,lon,ref_id,status,flags,uncertainty_m,radius95_m,p_correct\n"
                   "a.jpg,48.8584,2.2945,r1,fix,,25,60,0.97\n")
    gt = tmp_path / "g" / "gt.csv"
    gt.parent.mkdir()
    gt.write_text("file,lat,lon\na.jpg,48.8606,2.3376\n")
    before = _sha(tmp_path)
    for d in (tmp_path, gt.parent, res):
        assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt),
                     "--integrity-out", str(d), "--overwrite"]) == 2, d
        assert _sha(tmp_path) == before
    assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt)]) == 0
    assert (tmp_path / "r_integrity" / "integrity.json").is_file()


def test_build_map_out_never_holds_an_input(demo_map, demo_data, tmp_path, caplog):
    m = tmp_path / "map"
    shutil.copytree(demo_map, m)
    coords = m / "coords.csv"  # inputs kept inside an earlier map of ours
    shutil.copy(demo_data / "coords.csv", coords)
    npy = m / "d.npy"
    np.save(npy, np.zeros((71, 8), np.float32))
    (m / "teach").mkdir()
    (m / "teach" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    before = _sha(m)
    assert main(["build-map", "--descriptors", str(npy), "--coords", str(coords), "--out",
                 str(m), "--descriptor", "vlad_rootsift_fast", "--overwrite"]) == 2
    assert main(["build-map", "--images", str(demo_data / "images"), "--coords", str(coords),
                 "--out", str(m), "--overwrite"]) == 2
    assert main(["build-map", "--bag", str(m / "teach"), "--out", str(m),
                 "--overwrite"]) == 2
    assert _sha(m) == before
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 3 and all("contains the input" in e for e in errors), errors
