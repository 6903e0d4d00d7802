"""Verification on real maps (the 71 shipped demo images): the feature store written by the
builders, the leave-one-out calibration, featureless frames, damaged stores, maps without
features, map add/remove, and the CLI's results, evaluation and match drawings."""

from __future__ import annotations

import csv
import json
import logging
import math
import shutil

import numpy as np
import pytest

from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
from vlm_vpr_ros.localization.verification.stage import VerificationConfig, Verifier
from vlm_vpr_ros.maps.features import FeatureStore
from vlm_vpr_ros.maps.reference_map import ReferenceMap


def first_rows(demo_data, n: int, path):
    """The first ``n`` rows of the demo coordinates, and a coordinates CSV of them."""
    rows = list(csv.DictReader(open(demo_data / "coords.csv")))[:n]
    path.write_text("file,lat,lon\n" + "".join(f"{r['file']},{r['lat']},{r['lon']}\n"
                                               for r in rows))
    return rows, path


def featureless_frames() -> dict[str, np.ndarray]:
    """What a robot camera sends when it sees nothing: lens cap, overexposure, fog, noise."""
    rng = np.random.default_rng(0)
    h, w = 480, 640
    grad = np.repeat(np.linspace(0, 255, w, dtype=np.uint8)[None, :, None], h, 0)
    return {"black": np.zeros((h, w, 3), np.uint8), "white": np.full((h, w, 3), 255, np.uint8),
            "grey": np.full((h, w, 3), 128, np.uint8),
            "noise": rng.integers(0, 256, (h, w, 3)).astype(np.uint8),
            "gradient": np.repeat(grad, 3, 2), "lens_cap": (rng.normal(6, 3, (h, w, 3))
                                                           .clip(0, 255).astype(np.uint8))}


@pytest.fixture(scope="module")
def demo_pipe(demo_map):
    return LocalizationPipeline.open(demo_map)


def test_builder_stores_features_equal_to_a_fresh_extraction(demo_map, demo_data):
    m = ReferenceMap.load(demo_map)
    man = m.manifest
    sec = man["local_features"]
    assert sec["preset"] == "sift" and sec["feature"]["name"] == "sift"
    # vlad_rootsift_fast maps: SIFT at the descriptor's 480 px, 800 keypoints per query
    assert sec["feature"]["config"]["max_side"] == 480 and sec["query_max_keypoints"] == 800
    listed = [rel for e in sec["submaps"].values() for rel in e["files"].values()]
    assert all(rel in man["files"] for rel in listed)
    assert sec["bytes"] == sum(man["files"][rel]["bytes"] for rel in listed)
    store = FeatureStore.open(demo_map, man)
    from vlm_vpr_ros.localization.verification.components import create_feature

    x = create_feature("sift", sec["feature"]["config"])
    sub = m.submaps[0]
    for j in range(min(3, sub.count)):
        fresh = x.extract(load_image(demo_data / "images" / sub.ids[j]), sec["max_keypoints"])
        got = store.get(sub.id, j)
        assert np.array_equal(got.descriptors, fresh.descriptors)
        assert np.allclose(got.keypoints, fresh.keypoints, atol=0.25)  # fp16 coordinates
    # leave-one-out: 71 references, none within 25 m of another -> only wrong answers; each
    # reference a query under each of the four default conditions (docs/verification.md)
    from vlm_vpr_ros.mapping.local_features import DEGRADED_QUERIES
    from vlm_vpr_ros.localization.verification.conditions import DEFAULT_CONDITIONS

    doc = json.loads((demo_map / man["verification_calibration"]).read_text())
    assert doc["version"] == 2 and doc["conditions"] == list(DEFAULT_CONDITIONS)
    per = [doc["per_condition"][c]["queries"] for c in DEFAULT_CONDITIONS]
    assert per == [71] + [min(71, DEGRADED_QUERIES)] * 3
    assert doc["loo"]["queries"] == sum(per) and doc["loo"]["right"] == 0
    assert len(doc["null_scores"]) == sum(per)
    assert 0 < doc["min_long_side_px"] <= 480  # the smallest frame: fitted inside 480x360
    from vlm_vpr_ros.cli.map import map_info

    info = map_info(demo_map)["local_features"]
    assert info["bytes_per_reference"] == round(sec["bytes"] / 71) and info["calibrated"]


def test_featureless_frames_are_never_fixes(demo_pipe):
    for name, frame in featureless_frames().items():
        h = demo_pipe.localize_image(frame)
        assert h.status == "no_fix", (name, h.status_reason)
        assert h.verification == "verified" and h.p_correct < 0.95, name


def test_unverified_answers_on_an_uncalibrated_map_claim_no_small_radius(demo_map):
    """The demo map has no leave-one-out pairs for its posterior radii: with verification off,
    a black frame gets the spread of its candidates as radii (thousands of km on these
    world-wide references), not the posterior's 25 m floor, even as a fallback fix."""
    from vlm_vpr_ros.localization.verification.status import StatusPolicy, horizontal_sigma

    fallback = StatusPolicy(fallback_status="fix")
    off = LocalizationPipeline.open(demo_map, verification={"top_k": 0}, status=fallback)
    assert off.localizer.calibration_source.startswith("none")
    for name, frame in featureless_frames().items():
        h = off.localize_image(frame)
        assert "unverified" in h.flags and h.status_reason.startswith("fallback"), name
        top = h.candidates[:20]
        far = sorted(haversine_km(h.lat, h.lon, c.lat, c.lon) * 1000 for c in top)
        assert h.uncertainty_m >= far[int(np.ceil(0.68 * len(far))) - 1] - 1e-6, name
        assert horizontal_sigma(h) > 1e5, (name, horizontal_sigma(h))  # > 100 km


def test_fewer_verified_candidates_than_calibrated_claim_nothing(demo_map, demo_data, caplog):
    """p_correct was calibrated verifying 20 candidates: verifying fewer leaves look-alikes out
    (a higher inlier ratio for wrong answers), so p_correct is uncalibrated and nothing is a
    fix; verifying more keeps the (conservative) calibration."""
    from vlm_vpr_ros.evaluation.demo import make_query

    r = next(csv.DictReader(open(demo_data / "coords.csv")))
    q = make_query(load_image(demo_data / "images" / r["file"]), np.random.default_rng(0))
    few = LocalizationPipeline.open(demo_map, verification={"top_k": 5})
    assert not few.verifier.model.calibrated and "below the 20 candidates" in caplog.text
    h = few.localize_image(q)
    assert h.verification == "verified" and math.isnan(h.p_correct) and h.status == "no_fix"
    assert h.status_reason == "uncalibrated verification"
    more = LocalizationPipeline.open(demo_map, verification={"top_k": 30})
    assert more.verifier.model.calibrated and more.localize_image(q).status == "fix"


def test_a_mapped_place_is_verified_reranked_and_fixed(demo_pipe, demo_data):
    from vlm_vpr_ros.evaluation.demo import make_query

    assert demo_pipe.verifier.reuses_sift_of(demo_pipe.descriptor)  # one SIFT pass per query
    rows = list(csv.DictReader(open(demo_data / "coords.csv")))
    fixes = right = 0
    for i, r in enumerate(rows[:8]):
        q = make_query(load_image(demo_data / "images" / r["file"]), np.random.default_rng(i))
        h = demo_pipe.localize_image(q)
        err = haversine_km(float(r["lat"]), float(r["lon"]), h.lat, h.lon) * 1000
        right += err <= 25
        if h.status == "fix":
            fixes += 1
            assert err <= 25 and h.inliers > 20 and h.p_correct >= 0.95
            # a verified place: sigma of tens of metres, radii from the 25 m place disc
            assert h.uncertainty_m <= 25 and h.radius95_m <= 25
            assert h.candidates[0].inliers == h.inliers and "verified" in h.flags
    assert fixes >= 6 and right >= fixes
    # the same query with verification off: today's answer, unverified, no fix
    off = LocalizationPipeline.open(demo_pipe.map.path, verification={"top_k": 0})
    h = off.localize_image(make_query(load_image(demo_data / "images" / rows[0]["file"]),
                                      np.random.default_rng(0)))
    assert h.status == "no_fix" and "unverified" in h.flags and math.isnan(h.p_correct)


def copy_map(src, dst):
    shutil.copytree(src, dst)
    return dst


def test_damaged_or_foreign_feature_store(demo_map, tmp_path, caplog):
    m = copy_map(demo_map, tmp_path / "m")
    man = json.loads((m / "manifest.json").read_text())
    rel = next(iter(man["local_features"]["submaps"].values()))["files"]["descriptors"]
    with open(m / rel, "r+b") as fh:
        fh.truncate(100)
    with pytest.raises(MapError, match=rf"{rel} has 100 bytes, manifest says"):
        Verifier(ReferenceMap.load(m), VerificationConfig(required=True))
    v = Verifier(ReferenceMap.load(m), VerificationConfig())  # optional: warn, unverified
    assert not v.enabled and "truncated" in v.unavailable and "answers are unverified" in \
        caplog.text
    pipe = LocalizationPipeline.open(m)
    h = pipe.localize_image(featureless_frames()["noise"])
    assert h.status == "no_fix" and "unverified" in h.flags
    # features of another type than the manifest says, or one this software does not know:
    # refused at open, never matched against the query's
    for field, value, match in (("dtype", "float16", r"lf_desc.npy is uint8\(.*expected f2"),
                                ("name", "orb", "unknown local feature 'orb'")):
        m2 = copy_map(demo_map, tmp_path / f"m2{field}")
        man = json.loads((m2 / "manifest.json").read_text())
        man["local_features"]["feature"][field] = value
        (m2 / "manifest.json").write_text(json.dumps(man))
        with pytest.raises(MapError, match=match):
            Verifier(ReferenceMap.load(m2), VerificationConfig(required=True))
        assert not Verifier(ReferenceMap.load(m2), VerificationConfig()).enabled
    # a submap without features
    m3 = copy_map(demo_map, tmp_path / "m3")
    man = json.loads((m3 / "manifest.json").read_text())
    man["local_features"]["submaps"].pop(man["submaps"][0]["id"])
    (m3 / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(MapError, match="has no feature files"):
        Verifier(ReferenceMap.load(m3), VerificationConfig(required=True))


def test_map_without_features_verifies_from_images_but_claims_nothing(demo_data, tmp_path,
                                                                     caplog):
    from vlm_vpr_ros.mapping.build_images import build_map

    rows, coords = first_rows(demo_data, 14, tmp_path / "c.csv")
    m = tmp_path / "map"
    build_map(demo_data / "images", coords, m, descriptor="vlad_rootsift_fast",
              descriptor_config={"max_side": 320}, clusters=2, progress=False,
              local_features="none")
    assert "local_features" not in json.loads((m / "manifest.json").read_text())
    q = load_image(demo_data / "images" / rows[3]["file"])
    h = LocalizationPipeline.open(m).localize_image(q)
    assert h.verification.startswith("unverified") and h.status == "no_fix"
    with pytest.raises(MapError, match="stores no local features"):
        LocalizationPipeline.open(m, verification={"required": True})
    pipe = LocalizationPipeline.open(m, verification={"images_dir": str(demo_data / "images")})
    h = pipe.localize_image(q)
    # verified from the images (the copy matches itself), but no calibration: no claim
    assert h.verification == "verified" and h.inliers > 50 and h.ref_id == rows[3]["file"]
    assert math.isnan(h.p_correct) and h.status == "no_fix"
    assert h.status_reason == "uncalibrated verification"
    # a runtime verify_top_k that cannot be applied (required, nothing to verify against) is
    # refused once with a log line; the queries go on with the verifier they had
    off = LocalizationPipeline.open(m, verification={"top_k": 0, "required": True})
    with caplog.at_level(logging.ERROR):
        off.tune(None, 20)
        off.tune(None, 20)
    assert off.verifier.config.top_k == 0 and off.localize_image(q).status == "no_fix"
    assert caplog.text.count("verify_top_k 20 cannot be applied, keeping 0") == 1


def test_map_add_remove_keep_features_row_aligned(demo_half_map, demo_data, tmp_path):
    from vlm_vpr_ros.mapping.edit import add_references, remove_references

    rows, src = demo_half_map
    m = copy_map(src, tmp_path / "m")
    before = ReferenceMap.load(m)
    before_conds = json.loads((m / before.manifest["verification_calibration"]).read_text()
                              )["conditions"]
    store0 = FeatureStore.open(m, before.manifest)
    keep_id = before.submaps[0].ids[0]
    old = store0.get(before.submaps[0].id, 0)
    add_references(m, demo_data / "images", rows[36:41], progress=False)
    remove_references(m, [before.submaps[0].ids[1], rows[37][0]])
    after = ReferenceMap.load(m)
    store = FeatureStore.open(m, after.manifest)
    sec = after.manifest["local_features"]
    assert set(sec["submaps"]) == {s.id for s in after.submaps}
    for s in after.submaps:
        assert sec["submaps"][s.id]["count"] == s.count
    where = {i: (s.id, j) for s in after.submaps for j, i in enumerate(s.ids)}
    got = store.get(*where[keep_id])  # a kept reference: its bytes carried over
    assert np.array_equal(got.descriptors, old.descriptors)
    from vlm_vpr_ros.mapping.local_features import map_extractor

    refx = map_extractor(after, LocalizationPipeline.open(m).descriptor)
    new = refx.extractor.extract(load_image(demo_data / "images" / rows[39][0]),
                                 sec["max_keypoints"])
    assert np.array_equal(store.get(*where[rows[39][0]]).descriptors, new.descriptors)
    doc = json.loads((m / after.manifest["verification_calibration"]).read_text())
    assert doc["per_condition"]["full"]["queries"] == after.n_references == 36 + 5 - 2
    # recalibrated under the map's conditions, the degraded copies from the pictures the record
    # holds: it follows the edit (the removed references leave it, the ones added from the
    # recorded folder join it), so every reference of the edited map has its degraded copies
    assert doc["conditions"] == before_conds and len(before_conds) > 1
    assert all(doc["per_condition"][c]["queries"] == after.n_references
               for c in before_conds[1:])


def test_cli_results_evaluate_and_save_matches(demo_map, demo_data, tmp_path, capsys):
    from vlm_vpr_ros.cli import main
    from vlm_vpr_ros.evaluation.demo import make_query

    rows = list(csv.DictReader(open(demo_data / "coords.csv")))[:6]
    qdir = tmp_path / "q"
    qdir.mkdir()
    import cv2

    for i, r in enumerate(rows):
        q = make_query(load_image(demo_data / "images" / r["file"]), np.random.default_rng(i))
        cv2.imwrite(str(qdir / r["file"]), cv2.cvtColor(q, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(qdir / "black.jpg"), np.zeros((480, 640, 3), np.uint8))
    gt = tmp_path / "gt.csv"
    gt.write_text("file,lat,lon\n" + "".join(f"{r['file']},{r['lat']},{r['lon']}\n"
                                             for r in rows) + "black.jpg,0.5,0.5\n")
    res, out = tmp_path / "res.csv", tmp_path / "matches"
    assert main(["localize", "--map", str(demo_map), "--images", str(qdir), "--queries",
                 str(gt), "--out", str(res), "--save-matches", str(out), "--ground-truth",
                 str(gt), "--reference-images", str(demo_data / "images")]) == 0
    got = {r["file"]: r for r in csv.DictReader(open(res))}
    assert got["black.jpg"]["status"] == "no_fix"
    fixes = [r for r in got.values() if r["status"] == "fix"]
    assert fixes and all(float(r["p_correct"]) >= 0.95 and int(r["inliers"]) > 20
                         for r in fixes)
    assert len(got[rows[0]["file"]]["top_ids"].split("|")) == 20
    drawn = sorted(p.name for p in out.iterdir())
    assert f"{rows[0]['file']}.jpg" in drawn and load_image(out / drawn[0]).shape[0] > 300
    capsys.readouterr()
    assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt), "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    n_fix = len(fixes)
    assert ev["fixes"]["n"] == n_fix and ev["fixes"]["rate_pct"] == round(100 * n_fix / 7, 2)
    # recall@k recomputed from the CSV's candidate positions
    truth = {r["file"]: (float(r["lat"]), float(r["lon"])) for r in rows}
    truth["black.jpg"] = (0.5, 0.5)

    def err_m(la, lo, f):
        return haversine_km(la, lo, *truth[f]) * 1000

    r1 = sum(1 for f, r in got.items()
             if err_m(*map(float, r["top_positions"].split("|")[0].split()), f) <= 25)
    assert ev["recall_pct"]["@1"] == round(100 * r1 / 7, 2)
    # --only-wrong draws only the answers more than 25 m off
    out2 = tmp_path / "wrong"
    assert main(["localize", "--map", str(demo_map), "--images", str(qdir), "--queries",
                 str(gt), "--out", str(tmp_path / "r2.csv"), "--save-matches", str(out2),
                 "--only-wrong", "--ground-truth", str(gt)]) == 0
    wrong = {f for f, r in got.items() if err_m(float(r["lat"]), float(r["lon"]), f) > 25}
    names = {p.name for p in out2.iterdir()} if out2.exists() else set()
    assert "black.jpg" in wrong and names <= {f"{f}.jpg" for f in wrong}


def test_calibrate_adds_the_users_wrong_answers(demo_map, demo_data, tmp_path):
    """``vlm-vpr calibrate``: the inlier ratios of labelled answers more than 25 m off join the
    map's leave-one-out wrong answers; p_correct then rests on both."""
    from vlm_vpr_ros.cli import main
    from vlm_vpr_ros.localization.verification.p_correct import PCorrect, load_doc

    m = copy_map(demo_map, tmp_path / "m")
    rows = list(csv.DictReader(open(demo_data / "coords.csv")))[:12]
    gt = tmp_path / "gt.csv"  # half of the labels moved 1 km: those answers are wrong
    gt.write_text("file,lat,lon\n" + "".join(
        f"{r['file']},{float(r['lat']) + (0.009 if i % 2 else 0.0)},{r['lon']}\n"
        for i, r in enumerate(rows)))
    res = tmp_path / "res.csv"
    assert main(["localize", "--map", str(m), "--images", str(demo_data / "images"),
                 "--queries", str(gt), "--out", str(res)]) == 0
    got = list(csv.DictReader(open(res)))
    truth = {r["file"]: (float(r["lat"]), float(r["lon"])) for r in csv.DictReader(open(gt))}
    wrong = sorted(round(float(r["inlier_ratio"]), 4) for r in got
                   if haversine_km(float(r["lat"]), float(r["lon"]), *truth[r["file"]])
                   * 1000 > 25)
    assert len(wrong) >= 6
    assert main(["calibrate", "--results", str(res), "--ground-truth", str(gt),
                 "--map", str(m)]) == 0
    doc = load_doc(ReferenceMap.load(m))
    assert doc["user"]["null_scores"] == wrong and doc["user"]["queries"] == 12
    model = PCorrect.from_doc(doc)
    from vlm_vpr_ros.mapping.local_features import DEGRADED_QUERIES

    n = 71 + 3 * min(71, DEGRADED_QUERIES)  # leave-one-out wrong answers, four conditions
    assert len(model.null_scores) == n + len(wrong) and "user (12 labelled" in model.source
    # those wrong answers are copies of mapped images (high scores): an answer scoring like the
    # 4th strongest of them was a fix before (p 1 - 1/(n+1)) and is none now (1 - 5/(n+7))
    before = PCorrect.from_doc({**doc, "user": None})
    assert before.p_correct(wrong[-4]) == pytest.approx(1 - 1 / (n + 1)) and \
        1 - 1 / (n + 1) >= 0.99
    k = n + len(wrong) + 1
    assert model.p_correct(wrong[-4]) == pytest.approx(1 - 5 / k) and 1 - 5 / k < 0.99
