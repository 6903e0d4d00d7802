"""The verification calibration of a map built from a folder of images reads its degraded query
conditions from the pictures the build recorded (folder + size/sha256), checked picture by
picture: `vlm-vpr calibrate` without `--reference-images` and the recalibration after `map
remove` keep the map's conditions instead of falling back to full size only."""

from __future__ import annotations

import logging
import shutil

import pytest

from vlm_vpr_ros.localization.verification.p_correct import load_doc
from vlm_vpr_ros.mapping.edit import remove_references
from vlm_vpr_ros.mapping.local_features import calibrate_map, calibrated_conditions
from vlm_vpr_ros.maps.reference_map import ReferenceMap

from source_pictures import build_from_demo, copy_with_pictures

N = 8
CONDS = ["full", "fit480x360"]  # not the default set: an edit must keep exactly these


@pytest.fixture(scope="module")
def built(tmp_path_factory, demo_data):
    """(pictures folder, map, ids): a SIFT map built with ``build_map`` from eight demo
    pictures, calibrated for ``CONDS``."""
    return build_from_demo(demo_data, tmp_path_factory.mktemp("calibrate_sources"), N,
                           calibration_conditions=",".join(CONDS))


def _copy(built, tmp_path):
    """A private copy of the pictures and of the map, recording that copy as its source."""
    pics, m, ids = built
    p2, m2, _ = copy_with_pictures(pics, m, tmp_path)
    return p2, m2, ids


def test_build_calibrates_the_chosen_conditions(built):
    _, m, _ = built
    doc = load_doc(ReferenceMap.load(m))
    assert doc["conditions"] == CONDS
    assert doc["per_condition"]["fit480x360"]["queries"] == N  # every reference, degraded
    assert calibrated_conditions(ReferenceMap.load(m)) == CONDS


def test_calibrate_reads_the_recorded_pictures(built, tmp_path):
    """No ``images_dir`` and no ``images/`` in the map: the degraded queries come from the
    folder the build recorded (before: 'no reference images reachable', full size only)."""
    _, m, _ = _copy(built, tmp_path)
    doc = calibrate_map(ReferenceMap.load(m), conditions=CONDS)
    assert doc["conditions"] == CONDS
    assert doc["per_condition"]["fit480x360"]["queries"] == N


def test_a_changed_picture_is_skipped_by_name(built, tmp_path, caplog):
    """A picture whose bytes differ from the build's record is no calibration query (one
    WARN names it); the other pictures still are."""
    pics, m, ids = _copy(built, tmp_path)
    changed = pics / ids[3]
    changed.write_bytes(changed.read_bytes() + b"\0")  # same picture to a decoder, not a match
    with caplog.at_level(logging.WARNING):
        doc = calibrate_map(ReferenceMap.load(m), conditions=CONDS)
    assert doc["per_condition"]["fit480x360"]["queries"] == N - 1
    assert doc["per_condition"]["full"]["queries"] == N  # the stored features: unaffected
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(str(changed) in s and "changed since the map was built" in s for s in said)


def test_pictures_gone_calibrate_full_size_only_with_a_warning(built, tmp_path, caplog):
    pics, m, _ = _copy(built, tmp_path)
    shutil.rmtree(pics)
    with caplog.at_level(logging.WARNING):
        doc = calibrate_map(ReferenceMap.load(m), conditions=CONDS)
    assert doc["conditions"] == ["full"]
    assert any("no reference images reachable" in r.getMessage() for r in caplog.records)


def test_an_edit_keeps_the_maps_conditions(built, tmp_path):
    """``map remove`` recalibrates under the conditions the map was calibrated for, from the
    recorded pictures (before: the default four, of which only full size was reachable)."""
    _, m, ids = _copy(built, tmp_path)
    remove_references(m, [ids[0]])
    doc = load_doc(ReferenceMap.load(m))
    assert doc["conditions"] == CONDS
    assert doc["per_condition"]["fit480x360"]["queries"] == N - 1


def test_options_reach_the_degraded_queries(built, tmp_path, monkeypatch):
    """The feature and matcher options of a build or of ``calibrate`` (a learned preset's
    ``device=cuda``, ``threads``) reach the verifier that extracts and matches the degraded
    queries, not only the full-size matches (before: the degraded queries ran with the
    defaults, a GPU build's calibration on the CPU)."""
    import vlm_vpr_ros.mapping.local_features as lf

    _, m, _ = _copy(built, tmp_path)
    seen = []
    real = lf.Verifier

    def spy(ref_map, config, feature_options=None, matcher_options=None):
        seen.append((dict(feature_options or {}), dict(matcher_options or {})))
        return real(ref_map, config)  # SIFT takes neither: the spy only records them

    monkeypatch.setattr(lf, "Verifier", spy)
    doc = calibrate_map(ReferenceMap.load(m), conditions=CONDS,
                        feature_options={"device": "cuda"}, matcher_options={})
    assert seen == [({"device": "cuda"}, {})]
    assert doc["per_condition"]["fit480x360"]["queries"] == N


def test_calibrate_cli_checks_the_feature_options(built, tmp_path, caplog):
    """``vlm-vpr calibrate --conditions ... --feature-option`` hands the option to the
    degraded queries' extractor: one it does not know is exit 2 naming it, the old
    calibration kept."""
    from vlm_vpr_ros.cli import main

    _, m, _ = _copy(built, tmp_path)
    before = (m / "verification.json").read_bytes()
    with caplog.at_level(logging.ERROR):
        rc = main(["calibrate", "--map", str(m), "--conditions", ",".join(CONDS),
                   "--feature-option", "no_such_option=1"])
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert rc == 2 and any("unknown sift option" in s and "no_such_option" in s for s in said)
    assert (m / "verification.json").read_bytes() == before


def test_the_strongest_wrong_answers_are_recorded_and_explained(built):
    """verification.json keeps the strongest wrong leave-one-out answers by the references'
    ids (what sets the fix threshold), and ``calibrate`` names the ratio a fix needs: just
    above it ``p_correct`` reaches the level, just below it not."""
    from vlm_vpr_ros.cli.calibrate import threshold_summary
    from vlm_vpr_ros.localization.verification.p_correct import PCorrect

    _, m, ids = built
    doc = load_doc(ReferenceMap.load(m))
    sw = doc["strongest_wrong"]
    assert sw and len(sw) <= 10
    assert [r["score"] for r in sw] == sorted(doc["null_scores"], reverse=True)[:len(sw)]
    assert all(r["query"] in ids and r["answer"] in ids and r["query"] != r["answer"]
               and r["error_m"] > doc["place_radius_m"] for r in sw)
    # a user's wrong answers (calibrate --results) join the null set: the threshold follows
    with_user = {**doc, "user": {"null_scores": [7.5] * 30, "queries": 30, "results": "r.csv"}}
    for d in (doc, with_user):
        model = PCorrect.from_doc(d)
        for level in (0.5, 0.9):
            head = threshold_summary(d, level).splitlines()[0]
            t = float(head.split("above ")[1].split(" ")[0])
            assert model.p_correct(t - 1e-6) < level <= model.p_correct(t + 1e-6)
    assert "above 7.5 " in threshold_summary(with_user, 0.9)
    assert "no fix on this calibration" in threshold_summary(doc, 0.99)  # 8 + 8 queries
