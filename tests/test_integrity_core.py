"""Integrity of STATUS_FIX (issue 27, docs/verification.md): query conditions of the
calibration, the protection level, the alert limit of the status rule, calibration files of
both versions, and honest radii without verified evidence (issue 28)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vlm_vpr_ros.errors import ConfigError, MapError
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.localization.verification.p_correct import (
    INTEGRITY_RISK, PCorrect, calibration_doc, loo_records, support_spread_m, validate)
from vlm_vpr_ros.localization.verification.conditions import (DEFAULT_CONDITIONS,
                                                              ConditionWatch, parse_condition,
                                                              parse_conditions)
from vlm_vpr_ros.localization.verification.evidence import EvidenceConfig
from vlm_vpr_ros.mapping.local_features import photo_copies
from vlm_vpr_ros.localization.verification.status import (K_RISK, StatusPolicy, fix_status,
                                                          horizontal_sigma)
from vlm_vpr_ros.types import Hypothesis


# -- conditions ------------------------------------------------------------------------------
def test_conditions_fit_inside_the_box_keep_aspect_and_compress():
    rng = np.random.default_rng(0)
    portrait = rng.integers(0, 256, (1024, 745, 3)).astype(np.uint8)
    assert parse_condition("full").apply(portrait) is portrait
    small = parse_condition("fit640x480").apply(portrait)
    assert small.shape[0] == 480 and abs(small.shape[1] - 745 * 480 / 1024) <= 1
    assert parse_condition("fit480x360").apply(portrait).shape[:2] == (360, 262)
    tiny = np.zeros((100, 80, 3), np.uint8)
    assert parse_condition("fit640x480").apply(tiny).shape == tiny.shape  # never enlarged
    smooth = np.repeat(np.linspace(0, 255, 745, dtype=np.uint8)[None, :, None], 1024, 0)
    smooth = np.repeat(smooth, 3, 2)
    j = parse_condition("jpeg40_640x480").apply(smooth)
    assert j.shape[:2] == (480, 349) and j.dtype == np.uint8
    ref = parse_condition("fit640x480").apply(smooth)
    diff = np.abs(j.astype(int) - ref.astype(int))
    assert 0 < diff.mean() < 10  # compressed: changed, still the same picture
    assert [c.name for c in parse_conditions(None)] == list(DEFAULT_CONDITIONS)
    for bad in ("huge", "fit0x", "jpeg0_640x480", "jpeg101_640x480", "full,full", ""):
        with pytest.raises(ConfigError):
            parse_conditions(bad)


def test_condition_watch_warns_once_for_smaller_frames(caplog):
    w = ConditionWatch("map", 360, ["full", "fit480x360"])
    assert not w.check((480, 640)) and not w.check((360, 262))  # calibrated sizes
    assert w.check((240, 320)) and w.check((240, 320))
    assert caplog.text.count("smaller than the verification calibration covered") == 1
    assert not ConditionWatch("map", 0, []).check((10, 10))  # unknown: no per-frame claim


# -- protection level and the status rule ----------------------------------------------------
def _verified(p=0.99, pl=30.0, r68=21.0, r95=25.0) -> Hypothesis:
    h = Hypothesis(37.77, -122.42, "r", "*", r68, radius95_m=r95, p_correct=p,
                   p_correct_without_prior=p, protection_m=pl, verification="verified",
                   flags=("verified",))
    return h


def test_alert_limit_gates_fixes_and_sigma_holds_the_protection_level():
    policy = StatusPolicy()
    assert policy.fix_alert_limit_m == 50.0
    assert fix_status(_verified(pl=49.9), policy) == (True, "")
    ok, why = fix_status(_verified(pl=50.0), policy)
    assert not ok and "alert limit" in why
    ok, why = fix_status(_verified(pl=math.nan), policy)
    assert not ok and why == "no protection level"
    assert fix_status(_verified(pl=80.0), StatusPolicy(fix_alert_limit_m=100.0))[0]
    # the Gaussian of the published covariance holds the PL at the integrity risk
    for pl in (5.0, 30.0, 49.0, 400.0):
        s = horizontal_sigma(_verified(pl=pl))
        assert s * math.sqrt(-2 * math.log(INTEGRITY_RISK)) >= pl - 1e-9
    assert abs(K_RISK - 3.7169) < 1e-3


@pytest.mark.parametrize("bad", [0.0, -5.0, math.nan, math.inf, "50", None, True])
def test_alert_limit_must_be_a_positive_number(bad):
    with pytest.raises(ConfigError, match="fix_alert_limit_m"):
        StatusPolicy(fix_alert_limit_m=bad)


def test_support_spread_is_the_farthest_substantially_verified_reference():
    lat = np.array([37.7700, 37.7703, 37.7710, 37.7800, 37.7900])
    lon = np.array([-122.4200, -122.4200, -122.4200, -122.4200, -122.4200])
    inl = np.array([100, 40, 26, 12, 3])  # 26 >= a quarter of 100; 12 is the noise level
    want = haversine_km(lat[0], lon[0], lat[2], lon[2]) * 1000
    assert support_spread_m(lat, lon, inl, 0, 12) == pytest.approx(want, rel=1e-9)
    assert support_spread_m(lat, lon, np.array([100, 20, 20, 20, 20]), 0, 12) == 0.0
    assert support_spread_m(lat, lon, np.array([10, 9, 9, 9, 9]), 0, 12) == 0.0


def test_calibration_doc_counts_conditions_and_both_versions_load():
    coords = np.array([[37.77 + i * 1e-3, -122.42] for i in range(6)])
    # every winner is 111 m or more from its query: all three answers are wrong
    recs = [("full", 0, [1, 2, 3], np.array([80, 5, 3])),
            ("fit640x480", 2, [3, 4, 5], np.array([30, 29, 2])),
            ("full", 4, [4 + 0, 5], np.array([0, 0]))]
    doc = calibration_doc(recs, coords, 20, EvidenceConfig(), ["full", "fit640x480"], 360, 1.0)
    assert doc["version"] == 2 and doc["conditions"] == ["full", "fit640x480"]
    assert doc["per_condition"]["full"]["queries"] == 2
    assert doc["per_condition"]["fit640x480"]["wrong"] == 1
    assert doc["loo"]["wrong"] + doc["loo"]["right"] == 3
    assert doc["protection"]["residual_m"] >= doc["place_radius_m"]
    m = PCorrect.from_doc(validate(doc, "t"))
    assert m.conditions == ("full", "fit640x480") and m.min_long_side_px == 360
    old = {k: v for k, v in doc.items()
           if k not in ("conditions", "protection", "min_long_side_px", "per_condition")}
    old["version"] = 1
    m1 = PCorrect.from_doc(validate(old, "t"))  # a map calibrated before conditions existed
    assert m1.calibrated and m1.conditions == () and m1.residual_m == 25.0
    broken = dict(doc, protection={"residual_m": -1, "integrity_risk": 1e-3})
    with pytest.raises(MapError, match="protection"):
        validate(broken, "t")
    with pytest.raises(MapError, match="conditions"):
        validate(dict(doc, conditions=[]), "t")



def test_leave_one_out_leaves_out_every_copy_of_the_photo():
    """A photo stored twice (here at a look-alike place 5,000 km away) is left out with its
    copies: the held-out photo never meets itself; the other photo of the place still meets
    both copies of its pair, so the ambiguity stays in the calibration."""
    vecs = np.array([[1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    copies = photo_copies([vecs[:3], vecs[3:]])  # two "submaps": rows count globally
    assert copies == {0: (2,), 2: (0,), 1: (3,), 3: (1,)}
    assert photo_copies([vecs[4:], vecs[:1]]) == {}
    # rows 0, 1 at X; their copies 2, 3 at Y 5,000 km away; row 4 elsewhere
    coords = np.array([[37.77, -122.42], [37.7701, -122.42], [-33.87, 151.2],
                       [-33.8701, 151.2], [48.85, 2.35]])

    def search(g, k):  # by descriptor: the copies first (distance 0), then the rest
        d = ((vecs - vecs[g]) ** 2).sum(1)
        return sorted((float(d[j]), j) for j in range(5))[:k]

    def inliers_of(q, refs):  # identical photos match best, same place next
        return np.array([300 if r is q else 60 for r in refs])

    feats = [object() for _ in range(5)]
    kw = dict(features_of=lambda g: feats[g], inliers_of=inliers_of, top_k=2, max_queries=5)
    seen = {qi: cand for _, qi, cand, _ in loo_records(coords, search, **kw,
                                                       copies_of=lambda g: copies.get(g, ()))}
    assert all(j not in (qi, *copies.get(qi, ())) for qi, cand in seen.items() for j in cand)
    assert set(seen[0]) == {1, 3}  # the place's other photo and its look-alike copy: a tie
    old = {qi: cand for _, qi, cand, _ in loo_records(coords, search, **kw)}
    assert old[0][0] == 2  # without the rule the photo meets itself at the look-alike

# -- issue 28: no verified evidence, honest radii ---------------------------------------------
@pytest.mark.fault("no_evidence_twice_mapped")
def test_no_evidence_on_a_map_with_one_picture_twice_claims_no_small_radius(demo_data, tmp_path,
                                                                          caplog):
    """A map holding one picture twice at one place has leave-one-out pairs, so its posterior
    radii count as calibrated (25 m floor): a frame without a single inlier against any
    candidate (32x32, 8000x100, 10x4000) must get the candidates' spread as its radii, not
    25 m, and no protection level below the alert limit. On the same map: frames smaller than
    the calibration covered are flagged (warned once); a version-1 calibration still answers."""
    import csv
    import shutil

    import cv2

    from vlm_vpr_ros.files.images import load_image
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.localization.verification.status import horizontal_sigma
    from vlm_vpr_ros.mapping.build_images import build_map

    rows = list(csv.DictReader(open(demo_data / "coords.csv")))[:12]
    img = tmp_path / "img"
    img.mkdir()
    for r in rows:
        shutil.copy(demo_data / "images" / r["file"], img / r["file"])
    twin = "twin_" + rows[0]["file"]
    shutil.copy(demo_data / "images" / rows[0]["file"], img / twin)
    lines = [f"{r['file']},{r['lat']},{r['lon']}" for r in rows]
    lines.append(f"{twin},{rows[0]['lat']},{rows[0]['lon']}")  # the same picture, same place
    (tmp_path / "c.csv").write_text("file,lat,lon\n" + "\n".join(lines) + "\n")
    build_map(img, tmp_path / "c.csv", tmp_path / "map", descriptor="vlad_rootsift_fast",
              partition="kmeans", clusters=2, progress=False,
              calibration_conditions="full,fit480x360")
    pipe = LocalizationPipeline.open(tmp_path / "map")
    assert not pipe.localizer.calibration_source.startswith("none")  # "calibrated" radii
    assert pipe.verifier.model.conditions == ("full", "fit480x360")
    rng = np.random.default_rng(3)
    for shape in ((32, 32, 3), (100, 8000, 3), (4000, 10, 3)):
        frame = rng.integers(0, 256, shape).astype(np.uint8)
        h = pipe.localize_image(frame)
        assert h.status == "no_fix" and h.inliers <= 12, shape
        far = sorted(haversine_km(h.lat, h.lon, c.lat, c.lon) * 1000 for c in h.candidates[:20])
        assert h.uncertainty_m >= far[int(np.ceil(0.68 * len(far))) - 1] - 1e-6, shape
        assert h.radius95_m > 1e5 and horizontal_sigma(h) > 1e4, (shape, h.radius95_m)
        assert not (h.protection_m < 50.0), (shape, h.protection_m)

    # frames smaller than the calibration covered: flagged, warned once
    import logging

    side = pipe.verifier.model.min_long_side_px
    assert 0 < side <= 480
    image = load_image(img / rows[1]["file"])
    scale = (side - 40) / max(image.shape[:2])
    small = cv2.resize(image, (round(image.shape[1] * scale), round(image.shape[0] * scale)),
                       interpolation=cv2.INTER_AREA)
    with caplog.at_level(logging.WARNING):
        flags = [pipe.localize_image(small).flags for _ in range(2)]
    assert all("uncalibrated_conditions" in f for f in flags)
    assert caplog.text.count("smaller than the verification calibration covered") == 1
    assert "uncalibrated_conditions" not in pipe.localize_image(image).flags
    # a map calibrated before query conditions existed (version 1) opens and answers as
    # before, every verified answer flagged uncalibrated_conditions
    from vlm_vpr_ros.localization.verification.p_correct import load_doc, save_doc
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    ref_map = ReferenceMap.load(tmp_path / "map")
    doc = load_doc(ref_map)
    old = {k: v for k, v in doc.items()
           if k not in ("conditions", "protection", "min_long_side_px", "per_condition")}
    save_doc(ref_map, {**old, "version": 1})
    v1 = LocalizationPipeline.open(tmp_path / "map")
    assert v1.verifier.model.calibrated and v1.verifier.model.conditions == ()
    h = v1.localize_image(image)
    assert h.verification == "verified" and "uncalibrated_conditions" in h.flags
    assert h.ref_id == rows[1]["file"] and math.isfinite(h.protection_m)
    # vlm-vpr calibrate --conditions recalibrates it under the query conditions again
    from vlm_vpr_ros.cli import main

    assert main(["calibrate", "--map", str(tmp_path / "map")]) == 2  # nothing asked
    assert main(["calibrate", "--map", str(tmp_path / "map"), "--conditions", "fit1x"]) == 2
    assert main(["calibrate", "--map", str(tmp_path / "map"), "--conditions", "default",
                 "--degraded-queries", "0"]) == 2
    assert main(["calibrate", "--map", str(tmp_path / "map"), "--conditions", "default",
                 "--reference-images", str(img)]) == 0
    again = LocalizationPipeline.open(tmp_path / "map")
    assert again.verifier.model.conditions == tuple(DEFAULT_CONDITIONS)
    assert "uncalibrated_conditions" not in again.localize_image(image).flags

@pytest.mark.parametrize("bad", ["nan", "0", "-3", "inf", "abc"])
def test_cli_refuses_a_bad_alert_limit_with_exit_2(bad, tmp_path, capsys, caplog):
    from vlm_vpr_ros.cli import main

    (tmp_path / "imgs").mkdir()
    (tmp_path / "q.csv").write_text("file\na.jpg\n")
    argv = ["localize", "--map", str(tmp_path / "nomap"), "--images", str(tmp_path / "imgs"),
            "--queries", str(tmp_path / "q.csv"), "--out", str(tmp_path / "r.csv"),
            "--prior", "none", "--fix-alert-limit-m", bad]
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse: not a number
        rc = exc.code
    assert rc == 2
    said = capsys.readouterr().err + caplog.text
    assert "fix-alert-limit-m" in said.replace("_", "-")


@pytest.mark.parametrize("bad", [math.nan, 0.0, -1.0, "50"])
def test_node_refuses_a_bad_alert_limit(bad, tmp_path):
    from vlm_vpr_ros.runtime.params import RUNTIME_WRITABLE, from_params

    assert "fix_alert_limit_m" in RUNTIME_WRITABLE
    with pytest.raises(ConfigError, match="fix_alert_limit_m"):
        from_params({"map_dir": str(tmp_path), "fix_alert_limit_m": bad})
    cfg = from_params({"map_dir": str(tmp_path), "fix_alert_limit_m": 30.0})
    assert cfg.status_policy().fix_alert_limit_m == 30.0
