"""Verification stage, units: matching against brute force, the fundamental-matrix check on a
synthetic two-view scene, the evidence (inlier ratio, prior gate), p_correct against its
definition, the status stamp, and the registry's errors (docs/verification.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.localization.verification.components import (available_features,
                                                              available_matchers, create_feature,
                                                              create_matcher)
from vlm_vpr_ros.localization.verification.p_correct import PCorrect, verified_radius
from vlm_vpr_ros.localization.verification.evidence import EvidenceConfig, weigh
from vlm_vpr_ros.localization.verification.geometry import GeometryConfig, fundamental_inliers
from vlm_vpr_ros.localization.verification.presets import get_preset, preset_for_map
from vlm_vpr_ros.localization.verification.sift import rootsift
from vlm_vpr_ros.types import LocalFeatures

RNG = np.random.default_rng(7)


def feats(n: int, seed: int) -> LocalFeatures:
    r = np.random.default_rng(seed)
    return LocalFeatures(r.random((n, 2), np.float32) * 500,
                         r.integers(0, 120, (n, 128)).astype(np.uint8), (640, 480))


def brute_force_matches(q: LocalFeatures, r: LocalFeatures, ratio: float) -> set:
    """Mutual nearest neighbours + Lowe ratio, by loops over explicit distances."""
    a, b = rootsift(q.descriptors).astype(np.float64), rootsift(r.descriptors).astype(np.float64)
    d = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1))
    out = set()
    for i in range(len(a)):
        order = np.argsort(d[i])
        j, j2 = order[0], order[1]
        if d[i, j] <= ratio * d[i, j2] and int(np.argmin(d[:, j])) == i:
            out.add((i, int(j)))
    return out


def test_mutual_nn_ratio_equals_brute_force():
    q, r = feats(300, 1), feats(250, 2)
    # plant 60 true correspondences (slightly perturbed copies)
    r.descriptors[:60] = np.clip(q.descriptors[100:160].astype(int)
                                 + RNG.integers(-3, 4, (60, 128)), 0, 255).astype(np.uint8)
    m = create_matcher("nn")
    got = {tuple(x) for x in m.match(m.prepare(q), q, r).tolist()}
    assert got == brute_force_matches(q, r, 0.8)
    assert {(100 + k, k) for k in range(60)} <= got  # the planted pairs are found
    assert len(got) < 90  # and few chance pairs pass the ratio + mutual tests


def two_view(n_in: int, n_out: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projections of 3-D points into two cameras (rotation + translation) plus outliers."""
    r = np.random.default_rng(seed)
    X = np.c_[r.uniform(-4, 4, n_in), r.uniform(-3, 3, n_in), r.uniform(6, 14, n_in)]
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    ang = 0.15
    R = np.array([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0],
                  [-math.sin(ang), 0, math.cos(ang)]])
    t = np.array([1.0, 0.1, 0.2])

    def proj(P):
        p = (K @ P.T).T
        return p[:, :2] / p[:, 2:]
    a, b = proj(X), proj((R @ X.T).T + t)
    a += r.normal(0, 0.3, a.shape)
    b += r.normal(0, 0.3, b.shape)
    oa, ob = r.uniform(0, 640, (n_out, 2)), r.uniform(0, 480, (n_out, 2))
    truth = np.r_[np.ones(n_in, bool), np.zeros(n_out, bool)]
    return np.r_[a, oa], np.r_[b, ob], truth


def test_magsac_fundamental_keeps_the_true_correspondences():
    a, b, truth = two_view(120, 120)
    mask = fundamental_inliers(a, b, GeometryConfig())
    assert mask[truth].mean() >= 0.9  # recall of the true matches
    assert mask[~truth].mean() <= 0.1  # random pairs rarely fit the epipolar geometry
    # too few matches: no model, no inliers
    assert not fundamental_inliers(a[:8], b[:8]).any()
    # pure noise gives only a handful of chance inliers (the competitor floor's reason)
    noise = fundamental_inliers(*two_view(0, 60, seed=3)[:2])
    assert noise.sum() <= EvidenceConfig().competitor_floor


def positions(metres_east: list[float]) -> tuple[np.ndarray, np.ndarray]:
    lat0, lon0 = 37.78, -122.41
    lon = lon0 + np.array(metres_east) / (111_320.0 * math.cos(math.radians(lat0)))
    return np.full(len(lon), lat0), lon


def test_inlier_ratio_winner_and_competitors():
    lat, lon = positions([0, 10, 300, 900, 2000])
    ev = weigh(lat, lon, np.array([40, 200, 30, 9, -1]))
    # the winner is the most inliers; the 10-m neighbour is the same place, not a competitor
    assert ev.winner == 1 and ev.winner_inliers == 200 and ev.competitor_inliers == 30
    assert ev.score == pytest.approx(200 / 31) and ev.order[:3] == [1, 0, 2]
    # a competitor below the noise floor counts as the floor (12)
    ev = weigh(lat, lon, np.array([40, 0, 3, 0, 0]))
    assert ev.winner == 0 and ev.score == pytest.approx(40 / 13)
    # nothing above the noise level: the posterior's best stays, with a low score
    ev = weigh(lat, lon, np.array([5, 9, 0, 11, 0]))
    assert ev.winner == 0 and ev.score == pytest.approx(5 / 13)
    # no features at all (a lens cap): score 0
    assert weigh(lat, lon, np.zeros(5, int)).score == 0.0


def test_prior_gate_drops_far_look_alikes_and_picks_the_winner():
    # twins: the same view 0 m and 12,000 km away (a copy of the database on another continent)
    lat = np.array([37.78, -33.87, 37.79])
    lon = np.array([-122.41, 151.21, -122.42])
    inl = np.array([150, 150, 20])
    ev = weigh(lat, lon, inl)  # no prior: a tie, ratio ~1 -> never decisive
    assert ev.score == pytest.approx(150 / 151) and ev.gated == 0
    near_sf = np.array([0.0, -30.0, -0.5])  # prior log-density: Sydney 1e13 times less likely
    ev = weigh(lat, lon, inl, near_sf)
    assert ev.winner == 0 and ev.gated == 1
    assert ev.score == pytest.approx(150 / 21) and ev.score_ungated == pytest.approx(150 / 151)
    near_sydney = np.array([-30.0, 0.0, -30.0])  # a wrong prior picks the wrong twin
    ev = weigh(lat, lon, inl, near_sydney)
    assert ev.winner == 1 and ev.score > 10 * ev.score_ungated


def test_near_tie_between_places_goes_to_the_posterior_with_a_prior():
    """A place (candidates 1, 3: 10 m apart) and its look-alike 5,000 km away (0, 2) with about
    the same inliers; the prior makes the look-alike only 20x less likely (inside the gate), and
    the posterior ranks the place first. Without a prior the most inliers win (hloc); with it
    the near tie goes to the place the posterior ranks first, represented by its strongest
    candidate, and the answer stays a near tie (ratio < 2: never decisive)."""
    lat = np.array([12.0, 37.78, 12.0, 37.78009])
    lon = np.array([-75.0, -122.41, -75.0, -122.41])
    inl = np.array([170, 120, 150, 160])  # look-alike first by inliers
    order = [1, 3, 0, 2]  # posterior order: the place first (visual tie, prior nearer it)
    lat, lon, inl = lat[order], lon[order], inl[order]
    logp = np.array([0.0, 0.0, -3.0, -3.0])  # e^3 = 20x: not gated (gate 1e4)
    assert weigh(lat, lon, inl).winner == 2  # no prior: the most inliers (the look-alike)
    ev = weigh(lat, lon, inl, logp)
    assert ev.winner == 1 and ev.winner_inliers == 160  # the place, its strongest photo
    assert ev.gated == 0 and ev.score == pytest.approx(160 / 171)  # < 2: a near tie
    # a clear winner is not a tie: 2x the inliers of the other place keeps the most inliers
    ev = weigh(lat, lon, np.array([60, 50, 170, 150]), logp)
    assert ev.winner == 2 and ev.score == pytest.approx(170 / 61)


def test_p_correct_is_the_conformal_bound_of_wrong_answers():
    null = np.sort(RNG.gamma(2.0, 1.0, 199))
    model = PCorrect(null)
    for s in (0.0, 1.0, 2.5, 5.0, 100.0):
        expect = 1.0 - (1 + int((null >= s).sum())) / 200.0
        assert model.p_correct(s) == pytest.approx(expect)
    # a score above every wrong answer: 1 - 1/(n+1), never certainty
    assert model.p_correct(1e9) == pytest.approx(1 - 1 / 200)
    # held-out wrong answers from the same distribution pass 0.95 at most 5 % of the time, over
    # calibration sets and fresh answers alike (the conformal guarantee is marginal: one
    # calibration set alone may pass 6 %); an own generator, whatever ran before in the module
    rng = np.random.default_rng(27)
    passed = [np.mean([m.p_correct(s) >= 0.95 for s in rng.gamma(2.0, 1.0, 250)])
              for m in (PCorrect(np.sort(rng.gamma(2.0, 1.0, 199))) for _ in range(200))]
    assert abs(float(np.mean(passed)) - 0.05) <= 0.006
    # a near tie (ratio < 2: another place holds half the evidence) is capped at r / (1 + r),
    # whatever the map's wrong answers look like
    low = PCorrect(np.full(100, 0.1))
    assert low.p_correct(1.5) == pytest.approx(0.6) and low.p_correct(2.0) == pytest.approx(
        1 - 1 / 101)
    # fewer than 19 wrong answers can never support a 0.95 fix; no calibration: NaN
    assert PCorrect(np.arange(18.0)).p_correct(1e9) < 0.95
    assert math.isnan(PCorrect(np.zeros(0)).p_correct(10.0))


def test_verified_radius_only_narrows_at_the_fix_level():
    model = PCorrect(np.zeros(0), place_radius_m=25.0)
    # p 0.99 at level 0.95: uniform over the 25-m disc, r_q = 25 sqrt(q / p)
    assert verified_radius(model, 0.99, 0.68, 5000.0, 0.95) == pytest.approx(
        25 * math.sqrt(0.68 / 0.99))
    assert verified_radius(model, 0.99, 0.95, 5000.0, 0.95) == pytest.approx(
        25 * math.sqrt(0.95 / 0.99))
    # below the fix level (no bound holds) or unverified: the posterior's radius
    assert verified_radius(model, 0.9, 0.68, 5000.0, 0.95) == 5000.0
    assert verified_radius(model, math.nan, 0.68, 5000.0, 0.95) == 5000.0


def test_registry_presets_and_unknown_names():
    assert {"sift", "disk"} <= set(available_features())
    assert {"nn", "lightglue"} <= set(available_matchers())
    with pytest.raises(ConfigError, match="unknown local feature 'orb'; choices: aliked, disk, "
                                          "sift, xfeat"):
        create_feature("orb")
    with pytest.raises(ConfigError, match="unknown verification preset 'x'; choices: "
                                          "aliked_lightglue, disk_lightglue, sift, "
                                          "xfeat_lighterglue, xfeat_mnn"):
        get_preset("x")
    with pytest.raises(ConfigError, match="valid options"):
        create_feature("sift", {"max_sid": 100})
    # vlad maps: the sift preset takes the descriptor's own frame and keypoints
    p = preset_for_map("sift", {"name": "vlad_rootsift_fast",
                                "config": {"max_side": 480, "n_features": 800}})
    assert (p.feature_config["max_side"], p.query_max_keypoints, p.max_keypoints) == \
        (480, 800, 800)
    assert preset_for_map("sift", {"name": "eigenplaces"}).feature_config["max_side"] == 1024


def test_sift_features_strongest_first_and_lossless_uint8():
    import cv2

    img = np.zeros((240, 320, 3), np.uint8)
    for k in range(30):  # blobs and corners to detect
        c = (int(RNG.integers(20, 300)), int(RNG.integers(20, 220)))
        color = tuple(int(v) for v in RNG.integers(60, 255, 3))
        cv2.circle(img, c, int(RNG.integers(3, 12)), color, -1)
    x = create_feature("sift", {"max_side": 160})
    f = x.extract(img, 50)
    assert 0 < len(f) <= 50 and f.descriptors.dtype == np.uint8 and f.size == (160, 120)
    assert f.scale == pytest.approx(2.0) and f.keypoints.max() <= 160
    few = x.extract(img, 10)  # the 10 strongest are the first rows of the 50
    assert np.array_equal(few.keypoints, f.keypoints[:10])
    # a uniform frame has no features (the lens cap)
    assert len(x.extract(np.zeros((240, 320, 3), np.uint8), 50)) == 0


def test_a_map_whose_images_folder_is_gone_answers_unverified(tmp_path):
    """A map without stored features verifies against its images folder: when that folder is
    gone, answers are unverified (said at open), not "verified" with no reference readable."""
    from types import SimpleNamespace

    from vlm_vpr_ros.localization.verification.stage import Verifier

    ref_map = SimpleNamespace(path=tmp_path, manifest={"images": {"folder": "images"}},
                              descriptor_identity=None)
    gone = Verifier(ref_map)
    assert not gone.enabled and "images is gone" in gone.unavailable
    (tmp_path / "images").mkdir()
    assert Verifier(ref_map).enabled
