"""The same demo on every machine: the demo's tables (a small case: 6 places) are identical when
OpenCV runs without AVX, FAISS and OpenBLAS on their generic kernels and everything on one
thread (scripts/check_cpu_paths.py, each run a fresh process with the setting's environment),
and the look-alike step's twins are exact ties that the map's order breaks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from repo_scripts import load

check = load("scripts/check_cpu_paths.py")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    work = tmp_path_factory.mktemp("cpu_paths")
    lines: list[str] = []
    same, facts = check.compare(["default", "no-avx", "generic-faiss-blas", "all-forced"], 6,
                                work, nice=0, echo=lines.append)
    return work, same, facts, "\n".join(lines)


def test_tables_identical_under_forced_code_paths(runs):
    work, same, facts, printed = runs
    assert same, printed
    # the settings took effect: FAISS on its generic kernels, OpenBLAS on the forced core
    by = {f["setting"]: f for f in facts}
    assert by["generic-faiss-blas"]["faiss"] == "NONE" != by["default"]["faiss"]
    assert "Prescott" in by["generic-faiss-blas"]["blas"]
    assert "x1" in by["all-forced"]["blas"] and "x1" not in by["default"]["blas"]
    tables = json.loads((work / "default" / "demo.json").read_text())["tables"]
    assert set(tables) == {"map", "lookalike", "fixes"} and len(tables["map"]["rows"]) == 4
    for name in by:
        assert json.loads((work / name / "demo.json").read_text())["tables"] == tables


def test_differences_name_the_row():
    a = {"t": {"columns": ["", "x"], "rows": [["r1", "1"], ["r2", "2"]]}}
    b = {"t": {"columns": ["", "x"], "rows": [["r1", "1"], ["r2", "3"]]}}
    assert check.differences(a, a) == []
    diff = check.differences(a, b)
    assert len(diff) == 1 and "t / r2" in diff[0] and "'3'" in diff[0]
    assert "only in" in check.differences(a, {})[0]


def test_twins_are_exact_ties_broken_by_map_order(runs):
    """Independent reference: brute-force float64 distances from the stored descriptors. A
    look-alike's row equals its place's row bit for bit, so every query has a tie, and VPR only
    answers the one that comes first in the map (submap, then row)."""
    from vlm_vpr_ros.evaluation.lookalike import twin_id
    from vlm_vpr_ros.files.csvio import read_table
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    work = runs[0] / "default"
    look = ReferenceMap.load(work / "lookalike" / "map")
    vecs, ids = look.all_descriptors(), look.all_ids()
    row = {r: i for i, r in enumerate(ids)}
    assert len(ids) == 24
    for r in ids:
        assert np.array_equal(vecs[row[r]], vecs[row[twin_id(r)]]), r
        assert (work / "lookalike" / "refs" / r).read_bytes() == (
            work / "lookalike" / "refs" / twin_id(r)).read_bytes()
    q = np.load(work / "queries_descriptors.npy").astype(np.float64)
    d2 = ((q[:, None, :] - vecs[None].astype(np.float64)) ** 2).sum(-1)
    answers = [r["ref_id"] for r in read_table(work / "lookalike" / "results" / "results_0.csv",
                                               ("ref_id",))]
    for i, got in enumerate(answers):
        best = d2[i].min()
        tied = [ids[j] for j in np.flatnonzero(d2[i] == best)]
        assert len(tied) >= 2 and got == tied[0], (i, got, tied)  # the first in map order
        assert twin_id(got) in tied
