"""Issue 43, the command line: every `--help` prints what its author wrote (no argparse
escape left over), `evaluate` of an empty results CSV says so, and `evaluate --geojson` never
writes over an input or a file of the user's."""

from __future__ import annotations

import argparse
import json

import pytest

from vlm_vpr_ros.cli import build_parser, main


def _parsers(parser: argparse.ArgumentParser, path: list[str]):
    yield " ".join(path), parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, [*path, name])


def test_no_help_text_shows_a_doubled_percent_sign():
    seen = []
    for command, parser in _parsers(build_parser(), ["vlm-vpr"]):
        text = parser.format_help()  # what --help prints (argparse %-formats help strings)
        assert "%%" not in text and "%(" not in text, command
        seen.append(command)
    assert len(seen) > 20 and "vlm-vpr calibrate" in seen
    assert "68 % / 95 %" in dict(_parsers(build_parser(), ["vlm-vpr"]))[
        "vlm-vpr calibrate"].format_help()


COLUMNS = ("file,lat,lon,ref_id,status,flags,uncertainty_m,radius95_m,p_correct,confidence,"
           "top_positions,protection_m\n")


@pytest.fixture
def files(tmp_path):
    res, gt = tmp_path / "r.csv", tmp_path / "gt.csv"
    res.write_text(COLUMNS + "a.jpg,48.8584,2.2945,r1,fix,,25,60,0.97,0.9,,30\n")
    gt.write_text("file,lat,lon\na.jpg,48.8606,2.3376\n")
    return res, gt


def _one_error(caplog) -> str:
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "\n" not in errors[0], errors
    return errors[0]


@pytest.mark.parametrize("which", ["results", "ground_truth", "user_file", "folder"])
def test_geojson_never_replaces_an_input_or_a_users_file(files, tmp_path, caplog, which):
    res, gt = files
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes\n")
    target = {"results": res, "ground_truth": gt, "user_file": notes, "folder": tmp_path}[which]
    before = {p: p.read_bytes() for p in (res, gt, notes)}
    rc = main(["evaluate", "--results", str(res), "--ground-truth", str(gt), "--geojson",
               str(target), "--overwrite"])  # --overwrite is for our own outputs only
    assert rc == 2
    line = _one_error(caplog)
    assert str(target) in line and ("input" in line or "untouched" in line or "folder" in line)
    assert {p: p.read_bytes() for p in before} == before
    assert not (tmp_path / "r_integrity").exists()  # refused before any work


def test_geojson_through_another_path_of_an_input(files, tmp_path, caplog):
    res, gt = files
    (tmp_path / "link.csv").symlink_to(res)
    rc = main(["evaluate", "--results", str(tmp_path / "link.csv"), "--ground-truth", str(gt),
               "--geojson", str(tmp_path / "." / "r.csv")])
    assert rc == 2 and "is the input" in _one_error(caplog)
    assert res.read_text().startswith("file,lat")


def test_a_geojson_of_ours_is_replaced(files, tmp_path):
    res, gt = files
    out = tmp_path / "out.geojson"
    for _ in range(2):  # the second run replaces the first one's file
        assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt),
                     "--geojson", str(out), "--overwrite"]) == 0
        doc = json.loads(out.read_text())
        assert doc["type"] == "FeatureCollection" and len(doc["features"]) == 1


@pytest.mark.parametrize("which", ["results", "ground_truth"])
def test_evaluate_of_a_header_only_file_says_0_rows(files, tmp_path, caplog, capsys, which):
    res, gt = files
    if which == "results":
        res.write_text(COLUMNS)  # every column, no row
    else:
        gt.write_text("file,lat,lon\n")
    assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt)]) == 2
    line = _one_error(caplog)
    assert "0 rows" in line and str(res if which == "results" else gt) in line
    assert "older version" not in capsys.readouterr().out + line
