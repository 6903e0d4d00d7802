"""Issue 43: a calibration that cannot cover the query conditions asked for (the pictures the
map was built from moved) keeps the map's calibration: `calibrate --conditions` exits 2 naming
what is missing, and the recalibration after `map remove` keeps the earlier one with a WARN
(before: exit 0 and a full-size-only calibration in its place, so no more fixes)."""

from __future__ import annotations

import hashlib
import logging
import shutil

import pytest

from vlm_vpr_ros.cli import main
from vlm_vpr_ros.localization.verification.p_correct import load_doc
from vlm_vpr_ros.mapping.edit import remove_references
from vlm_vpr_ros.maps.reference_map import ReferenceMap

from source_pictures import build_from_demo, copy_with_pictures

N = 8
CONDS = ["full", "fit480x360"]


@pytest.fixture(scope="module")
def built(tmp_path_factory, demo_data):
    return build_from_demo(demo_data, tmp_path_factory.mktemp("calibrate43"), N,
                           calibration_conditions=",".join(CONDS))


def _sha(folder) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.iterdir()) if p.is_file()}


def _errors(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]


def test_calibrate_without_the_pictures_keeps_the_old_calibration(built, tmp_path, caplog):
    pics, m, _ = copy_with_pictures(built[0], built[1], tmp_path)
    moved = tmp_path / "moved"
    shutil.move(str(pics), moved)
    before = _sha(m)
    rc = main(["calibrate", "--map", str(m), "--conditions", ",".join(CONDS)])
    errors = _errors(caplog)
    assert rc == 2 and len(errors) == 1 and "\n" not in errors[0], errors
    assert "fit480x360" in errors[0] and str(pics) in errors[0]
    assert "old calibration was kept" in errors[0]
    assert _sha(m) == before  # verification.json and the manifest as they were
    assert load_doc(ReferenceMap.load(m))["conditions"] == CONDS
    caplog.clear()  # with the pictures where they are now: calibrated under both
    assert main(["calibrate", "--map", str(m), "--conditions", ",".join(CONDS),
                 "--reference-images", str(moved)]) == 0
    doc = load_doc(ReferenceMap.load(m))
    assert doc["conditions"] == CONDS and doc["per_condition"]["fit480x360"]["queries"] == N


def test_default_conditions_without_any_picture_are_refused(built, tmp_path, caplog):
    pics, m, _ = copy_with_pictures(built[0], built[1], tmp_path)
    for i in built[2]:  # every picture changed: none passes the build's record
        (pics / i).write_bytes((pics / i).read_bytes() + b"\0")
    before = _sha(m)
    assert main(["calibrate", "--map", str(m), "--conditions", "default"]) == 2
    (line,) = _errors(caplog)
    assert "none of" in line and "old calibration was kept" in line
    assert _sha(m) == before
    caplog.clear()  # full size needs no picture
    assert main(["calibrate", "--map", str(m), "--conditions", "full"]) == 0


def test_an_edit_without_the_pictures_keeps_the_earlier_calibration(built, tmp_path, caplog):
    pics, m, _ = copy_with_pictures(built[0], built[1], tmp_path)
    shutil.rmtree(pics)
    with caplog.at_level(logging.WARNING):
        remove_references(m, [built[2][0]])
    doc = load_doc(ReferenceMap.load(m))
    assert doc["conditions"] == CONDS  # not replaced by a full-size-only calibration
    assert doc["per_condition"]["fit480x360"]["queries"] == N
    said = " ".join(r.getMessage() for r in caplog.records)
    assert "keeps its earlier calibration" in said and "--reference-images" in said
