"""Fusion: the VLM error model (sphere-correct, fitted, validated), the posterior over candidates,
voting, soft submap choice, bad priors, no-match, calibration and ``vlm-vpr calibrate``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vlm_vpr_ros.errors import ConfigError, MapError
from vlm_vpr_ros.localization.fusion.calibration import (_sample_prior, conformal_factor,
                                                         load_calibration)
from vlm_vpr_ros.localization.fusion.error_model import (DEFAULT_ERROR_MODEL, ErrorModel,
                                                         fit_error_model, load_error_models)
from vlm_vpr_ros.localization.fusion.posterior import fuse
from vlm_vpr_ros.geodesy import EARTH_RADIUS_KM, MAX_DISTANCE_KM, haversine_km
from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
from vlm_vpr_ros.mapping.assemble import assemble_map
from vlm_vpr_ros.mapping.build_images import write_map_calibration
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.priors.provider import Prior, PriorResult

MODEL = ErrorModel((1.0, 20.0, 800.0), (0.3, 0.3, 0.2), 0.2, "test")


def prior_at(lat, lon, sigma_km=None):
    return PriorResult(Prior(lat, lon, "test", sigma_km), "test")


# -- error model ---------------------------------------------------------------------------------
def test_error_model_is_a_density_on_the_sphere():
    # integrate the areal density over the sphere: sum f(t) 2 pi R^2 sin t dt == 1
    t = np.linspace(0, math.pi, 400_001)
    f = np.exp(MODEL.log_density(t * EARTH_RADIUS_KM))
    ring = 2 * math.pi * EARTH_RADIUS_KM ** 2 * np.sin(t)
    assert np.trapezoid(f * ring, t) == pytest.approx(1.0, abs=2e-4)
    # the CDF is the integral of the density, up to the antipode
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] * ring[1:] + f[:-1] * ring[:-1])
                                           * np.diff(t))])
    for d in (0.5, 5.0, 100.0, 3000.0, MAX_DISTANCE_KM):
        i = int(round(d / EARTH_RADIUS_KM / (t[1] - t[0])))
        assert float(MODEL.cdf(d)) == pytest.approx(cum[i], abs=2e-4)
    assert float(MODEL.cdf(MAX_DISTANCE_KM)) == pytest.approx(1.0)
    for p in (0.1, 0.5, 0.68, 0.95):
        assert float(MODEL.cdf(MODEL.quantile(p))) == pytest.approx(p, abs=1e-6)


def test_small_scale_component_is_a_2d_gaussian():
    m = ErrorModel.single(2.0, uniform_weight=0.0)
    # Rayleigh: P(r <= k sigma) = 1 - exp(-k^2 / 2)
    for k in (0.5, 1.0, 1.5096, 2.4477):
        assert float(m.cdf(2.0 * k)) == pytest.approx(1 - math.exp(-k * k / 2), abs=1e-5)
    assert float(m.log_density(0.0)) == pytest.approx(-math.log(2 * math.pi * 4.0), abs=1e-6)


def test_fit_recovers_a_known_mixture():
    rng = np.random.default_rng(0)
    truth = ErrorModel((2.0, 50.0, 900.0), (0.3, 0.3, 0.2), 0.2)
    d = truth.sample_km(rng, 3000)
    # the sampler places priors at those distances on the sphere
    moved = [_sample_prior(10.0, 20.0, truth, np.random.default_rng(i)) for i in range(5)]
    for i, (la, lo) in enumerate(moved):
        want = truth.sample_km(np.random.default_rng(i), 1)[0]
        assert float(haversine_km(10.0, 20.0, la, lo)) == pytest.approx(want, rel=1e-6,
                                                                         abs=1e-6)
    fit, _ = fit_error_model(d)
    for km in (1, 5, 25, 200, 750, 2500):
        assert float(fit.cdf(km)) == pytest.approx(float(truth.cdf(km)), abs=0.03), km


def test_shipped_model_reproduces_published_gpt4o_accuracy():
    models = load_error_models()
    assert models.default == "pooled" and models.path == str(DEFAULT_ERROR_MODEL)
    assert {"gpt-4o", "pooled"} <= set(models.models)
    prov = models.provenance
    assert prov["sources"] and all(len(s["sha256"]) == 64 for s in prov["sources"])
    # published (README of ../shared, over all 237 images; 212 readable answers)
    published = {1: 20.68, 25: 51.90, 200: 64.98, 750: 75.53, 2500: 84.39}
    gpt = models.get("gpt-4o")
    for km, pct in published.items():
        assert 100 * float(gpt.cdf(km)) * 212 / 237 == pytest.approx(pct, abs=5.0), km
    assert models.for_source("openai:gpt-4o") is gpt
    assert models.for_source("recorded") is models.get("pooled")


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d.update(version=7), "format/version"),
    (lambda d: d["models"]["pooled"].update(weights=[0.5, 0.5, 0.5, 0.5]), "sum to"),
    (lambda d: d["models"]["pooled"].update(sigmas_km=[-1, 2, 3, 4]), "sigmas_km"),
    (lambda d: d["models"]["pooled"].pop("uniform_weight"), "uniform_weight"),
    (lambda d: d.update(default="nope"), "default 'nope'"),
])
def test_bad_error_model_file_stops_start_up(tmp_path, mutate, message):
    doc = json.loads(DEFAULT_ERROR_MODEL.read_text())
    mutate(doc)
    bad = tmp_path / "model.json"
    bad.write_text(json.dumps(doc))
    m, _, _ = _map()
    with pytest.raises(ConfigError, match=message) as exc:
        Localizer(m, LocalizerConfig(error_model=str(bad)))
    assert str(bad) in str(exc.value)
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(ConfigError, match="not valid JSON"):
        Localizer(m, LocalizerConfig(error_model=str(tmp_path / "x.json")))
    with pytest.raises(ConfigError, match="unknown error model"):
        Localizer(m, LocalizerConfig(error_model_name="gpt-5"))


# -- posterior ------------------------------------------------------------------------------------
def test_candidates_inside_the_prior_error_are_ordered_by_visual_evidence():
    rng = np.random.default_rng(1)
    lat = 37.77 + rng.uniform(-0.003, 0.003, 30)  # all within ~350 m of the prior
    lon = -122.42 + rng.uniform(-0.003, 0.003, 30)
    l2 = np.sort(rng.uniform(0.5, 1.5, 30))
    post = fuse(l2, lat, lon, visual_scale=0.05, prior=(37.77, -122.42), error_model=MODEL,
                vote_radius_m=1.0)
    assert post.best == 0
    assert list(np.argsort(-post.weights, kind="stable")) == list(range(30))


def test_far_look_alike_loses_to_a_near_one():
    # the same visual evidence (even slightly better far away): the prior decides
    lat, lon = np.array([40.0, -33.9]), np.array([-3.7, 151.2])  # Madrid-ish vs Sydney
    post = fuse(np.array([1.00, 0.99]), lat, lon, 0.05, prior=(40.2, -3.6), error_model=MODEL)
    assert post.best == 0 and post.weights[0] > 0.99
    # but a decisive visual match far away still wins over a poor one near the prior
    post = fuse(np.array([1.0, 0.0]), lat, lon, 0.01, prior=(40.2, -3.6), error_model=MODEL)
    assert post.best == 1


def test_geographic_vote_beats_a_lone_slightly_better_match():
    # three agreeing references within 10 m beat one slightly better isolated match
    lat = np.array([48.0, 45.0, 45.00005, 45.0001])
    lon = np.array([2.0, 7.0, 7.0, 7.0001])
    l2 = np.array([1.00, 1.02, 1.02, 1.03])
    post = fuse(l2, lat, lon, visual_scale=0.1)
    assert post.weights.argmax() == 0 and post.best in (1, 2, 3)
    assert post.votes[post.best] > post.votes[0]


def test_bad_priors_are_failed_priors_and_global_retrieval():
    m, desc, ids = _map()
    loc = Localizer(m)
    q = desc[ids.index("b_007")]
    ref = loc.localize(q, None)
    for lat, lon, sig in ((math.nan, 2.0, None), (95.0, 2.0, None), (10.0, 200.0, None),
                          (10.0, math.inf, None), (10.0, 20.0, -1.0), (10.0, 20.0, math.nan)):
        hyp = loc.localize(q, prior_at(lat, lon, sig))
        assert {"prior_failed", "prior_invalid", "no_prior"} <= set(hyp.flags) and hyp.flagged
        assert hyp.prior is None and hyp.ref_id == ref.ref_id
        assert math.isfinite(hyp.uncertainty_m) and hyp.uncertainty_m <= hyp.radius95_m


def test_zero_candidates_is_a_flagged_no_match():
    import faiss

    from vlm_vpr_ros.maps.reference_map import Submap

    ident = {"name": "synthetic", "dim": 8, "config": {}, "preprocessing": {}}
    empty = ReferenceMap({"descriptor": ident, "index": "flat",
                          "partition": {"method": "kmeans", "params": {}}},
                         [Submap("k000", (0.0, 0.0), np.zeros((0, 2)), [],
                                 faiss.IndexFlatL2(8))], {})
    for fusion in ("posterior", "paper"):
        loc = Localizer(empty, LocalizerConfig(fusion=fusion))
        hyp = loc.localize(np.zeros(8, np.float32), None)
        assert "no_match" in hyp.flags and hyp.flagged and hyp.candidates == []
        assert math.isnan(hyp.lat) and hyp.uncertainty_m == pytest.approx(MAX_DISTANCE_KM * 1e3)
        hyp = loc.localize(np.zeros(8, np.float32), prior_at(1.0, 2.0))
        assert "no_match" in hyp.flags and (hyp.lat, hyp.lon) == (1.0, 2.0)
        assert hyp.as_row()["flags"].endswith("no_match")


# -- soft submap choice ---------------------------------------------------------------------------
def _map(clusters=6, seed=0):
    """Six towns 300+ km apart, 20 references each with random descriptors."""
    rng = np.random.default_rng(seed)
    towns = [(40.0, -3.7), (48.9, 2.35), (52.5, 13.4), (41.9, 12.5), (59.3, 18.1),
             (38.7, -9.1)]
    coords, ids = [], []
    for t, (la, lo) in enumerate(towns):
        for i in range(20):
            coords.append((la + rng.normal(0, 0.01), lo + rng.normal(0, 0.01)))
            ids.append(f"{'abcdef'[t]}_{i:03d}")
    desc = rng.normal(size=(len(ids), 16)).astype(np.float32)
    ident = {"name": "synthetic", "dim": 16, "config": {}, "preprocessing": {}}
    return assemble_map(desc, np.array(coords), ids, ident, {}, "kmeans", clusters), desc, ids


def test_region_covers_the_prior_confidence_and_respects_the_budget():
    m, desc, ids = _map()
    narrow = Localizer(m, LocalizerConfig(global_merge_max_refs=0))
    # a precise prior (5 km) in Madrid: one town's submap only
    subs, flags = narrow.select_submaps(Prior(40.0, -3.7, "t", 5.0))
    assert len(subs) == 1 and not flags
    assert all(i.startswith("a_") for i in m.submaps[subs[0]].ids)
    # the wide VLM model: its 95 % region spans Europe -> every submap
    subs, _ = narrow.select_submaps(Prior(40.0, -3.7, "t"))
    assert sorted(subs) == list(range(len(m.submaps)))
    # budget: at most 45 references (two towns of 20), nearest first
    tight = Localizer(m, LocalizerConfig(global_merge_max_refs=0, max_region_refs=45))
    subs, flags = tight.select_submaps(Prior(40.0, -3.7, "t"))
    assert sum(m.submaps[i].count for i in subs) <= 45 and "region_budget" in flags
    assert {m.submaps[i].ids[0][0] for i in subs} == {"a", "f"}  # Madrid, then Lisbon
    # a prior in the ocean far from every submap's confidence region
    subs, flags = narrow.select_submaps(Prior(-40.0, -120.0, "t", 5.0))
    assert len(subs) == 1 and "prior_not_in_map" in flags


def test_prior_never_hides_the_best_visual_match_on_small_maps():
    m, desc, ids = _map()
    q = desc[ids.index("e_004")]  # Stockholm
    hyp = Localizer(m).localize(q, prior_at(40.0, -3.7, 5.0))  # a precise but wrong prior
    assert any(c.ref_id == "e_004" for c in hyp.candidates) and hyp.submap == "*"
    # without the global merge the region search alone cannot see it
    hyp = Localizer(m, LocalizerConfig(global_merge_max_refs=0)).localize(
        q, prior_at(40.0, -3.7, 5.0))
    assert all(c.ref_id.startswith("a_") for c in hyp.candidates)


# -- calibration ----------------------------------------------------------------------------------
def test_conformal_factor_finite_sample():
    r = np.arange(1, 101) / 100.0
    assert conformal_factor(r, 0.68) == pytest.approx(0.69)  # ceil(101 * 0.68) = 69th
    assert conformal_factor(r, 0.95) == pytest.approx(0.96)
    assert conformal_factor(r[:5], 0.95) == pytest.approx(0.05)  # n too small: the max
    assert conformal_factor([], 0.68) == 1.0


def test_build_time_calibration_is_one_optional_file(tmp_path):
    rng = np.random.default_rng(3)
    places = rng.uniform([40, -5], [41, -4], size=(60, 2))
    coords = np.repeat(places, 3, axis=0) + rng.normal(0, 2e-5, size=(180, 2))  # 3 views each
    base = rng.normal(size=(60, 32))
    desc = (np.repeat(base, 3, axis=0) + 1.2 * rng.normal(size=(180, 32))).astype(np.float32)
    ids = [f"r{i}" for i in range(180)]
    ident = {"name": "synthetic", "dim": 32, "config": {}, "preprocessing": {}}
    m = assemble_map(desc, coords, ids, ident, {}, "kmeans", 4)
    m.save(tmp_path / "old")
    old = Localizer(ReferenceMap.load(tmp_path / "old"))  # a map without calibration loads
    assert old.calibration == {} and old.calibration_source.startswith("none")
    m.save(tmp_path / "new")
    write_map_calibration(m, desc, coords)
    m2 = ReferenceMap.load(tmp_path / "new")
    assert m2.manifest["calibration"] == "calibration.json"
    assert "calibration.json" in m2.manifest["files"]
    cal = load_calibration(m2)
    assert cal["loo"]["queries"] == 180 and cal["visual_scale"] > 0
    assert 0 < cal["miss_prob"] < 0.5 and cal["beta"] > 0
    loc = Localizer(m2)
    assert loc.calibration_source.startswith("map leave-one-out")
    # the LOO-calibrated radii hold the truth of fresh views of the places as advertised
    errs, r68, r95 = [], [], []
    for k in range(60):
        q = (base[k] + 1.2 * rng.normal(size=32)).astype(np.float32)
        h = loc.localize(q, None)
        errs.append(float(haversine_km(h.lat, h.lon, *places[k])) * 1e3)
        r68.append(h.uncertainty_m)
        r95.append(h.radius95_m)
    cov68 = np.mean(np.array(errs) <= np.array(r68))
    cov95 = np.mean(np.array(errs) <= np.array(r95))
    assert 0.5 <= cov68 <= 0.9 and cov95 >= 0.85, (cov68, cov95)
    # a tampered calibration file is a MapError naming it
    (tmp_path / "new" / "calibration.json").write_text("{}")
    with pytest.raises(MapError, match="calibration.json"):
        Localizer(m2)


def test_cli_calibrate_sets_the_user_factors(tmp_path, capsys):
    from vlm_vpr_ros.cli import main

    m, desc, ids = _map()
    m.save(tmp_path / "map")
    rng = np.random.default_rng(4)
    rows, gt = [], []
    for i in range(40):  # errors 0..2 km, radii 100 m / 500 m: badly over-confident
        la, lo = 40.0 + i * 0.01, -3.7
        err_km = rng.uniform(0, 2)
        rows.append(f"q{i}.jpg,{la + err_km / 111.2:.7f},{lo},100.0,500.0,40.0")
        gt.append(f"q{i}.jpg,{la},{lo}")
    (tmp_path / "r.csv").write_text("file,lat,lon,uncertainty_m,radius95_m,prior_lat\n"
                                    + "\n".join(rows) + "\n")
    (tmp_path / "gt.csv").write_text("file,lat,lon\n" + "\n".join(gt) + "\n")
    args = ["calibrate", "--results", str(tmp_path / "r.csv"), "--ground-truth",
            str(tmp_path / "gt.csv"), "--map", str(tmp_path / "map")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "prior: 40 rows" in out and "wrote" in out
    loc = Localizer(ReferenceMap.load(tmp_path / "map"))
    k68, k95 = loc.calibration_factors(True)
    assert loc.calibration_source.startswith("user")
    # after calibration the radii cover 68 % / 95 % of these rows (conformal, same data)
    errs = np.array([float(haversine_km(*map(float, r.split(",")[1:3]),
                                        *map(float, g.split(",")[1:3]))) * 1e3
                     for r, g in zip(rows, gt)])
    assert np.mean(errs <= 100.0 * k68 * (1 + 1e-9)) >= 0.68
    assert np.mean(errs <= 500.0 * k95 * (1 + 1e-9)) >= 0.95
    assert loc.calibration_factors(False) == (1.0, 1.0)  # no rows without a prior
    # too few rows: exit 2 with a clear message
    (tmp_path / "few.csv").write_text("file,lat,lon,uncertainty_m,radius95_m\nq0.jpg,40,-3.7,"
                                      "5,9\n")
    assert main(args[:2] + [str(tmp_path / "few.csv")] + args[3:]) == 2


@pytest.mark.parametrize("q", [0.68, 0.95])
def test_mixture_radius_matches_a_scalar_bisection(q):
    """The vectorized radius search equals a plain 60-step scalar bisection (independent
    reference) for a continuous miss CDF and for a step-function one (searched with and
    without the step shortcut)."""
    from vlm_vpr_ros.localization.fusion.posterior import _mixture_radii

    rng = np.random.default_rng(5)
    d = np.sort(rng.uniform(0, 3000, 40))
    w = rng.dirichlet(np.ones(40)) * 0.7
    steps = np.sort(rng.uniform(0, 15000, 200))
    levels = np.arange(1, 201) / 200.0
    cdfs = {"smooth": (lambda r: 1.0 - np.exp(-np.asarray(r, dtype=float) / 800.0), None),
            "steps": (lambda r: np.searchsorted(steps, r, side="right") / len(steps), None),
            "steps, shortcut": (lambda r: np.searchsorted(steps, r, side="right") / len(steps),
                                (steps, levels))}
    for name, (cdf, step) in cdfs.items():
        got = _mixture_radii((q,), d, w, 0.3, cdf, step)[0]

        def mass(r):
            return w[d <= r].sum() + 0.3 * float(np.asarray(cdf(np.array([r])))[0])

        lo, hi = 0.0, MAX_DISTANCE_KM
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if mass(mid) >= q else (mid, hi)
        assert got == pytest.approx(hi, rel=1e-5, abs=5e-3), name
        assert mass(got) >= q - 1e-12


def test_step_shortcut_gives_the_grid_search_bit_for_bit():
    """The radius search without evaluating a step-function miss CDF (the map's background)
    returns exactly what the 64-point grid rounds return, on random mixtures with repeated
    steps, zero and full miss mass, points beyond every step and quantiles never reached."""
    from vlm_vpr_ros.localization.fusion.posterior import _mixture_radii

    rng = np.random.default_rng(31)
    for trial in range(400):
        n, m = int(rng.integers(1, 60)), int(rng.integers(1, 400))
        scale = 10.0 ** rng.uniform(-3, 4)
        d = rng.uniform(0, scale, n) * (rng.random(n) < 0.9)
        w = rng.dirichlet(np.ones(n)) * rng.uniform(0.0, 1.0)
        bd = np.sort(np.round(rng.uniform(0, scale * rng.uniform(0.1, 30), m),
                              int(rng.integers(0, 4))))  # rounded: repeated steps
        bcum = np.cumsum(rng.random(m) * (rng.random(m) < 0.7))
        bcum = bcum / bcum[-1] if bcum[-1] > 0 else np.ones(m)
        miss = float(rng.choice([0.0, 1.0, rng.uniform(0, 1)]))

        def cdf(r):
            k = np.searchsorted(bd, r, side="right")
            return np.where(k > 0, bcum[np.maximum(k - 1, 0)], 0.0)

        qs = (0.68, 0.95, float(rng.uniform(0, 1.2)))
        want = _mixture_radii(qs, d, w, miss, cdf)
        got = _mixture_radii(qs, d, w, miss, cdf, (bd, bcum))
        assert got == want, (trial, got, want)


def test_fuse_given_what_its_caller_computed_equals_fuse_computing_it():
    """The paper mode hands fuse() the distances to the prior it already computed, and the
    localizer the background weighted once per prior: the same posterior, vote, estimate and
    radii as fuse() computing them itself."""
    from vlm_vpr_ros.localization.fusion.posterior import prior_weighted_background

    rng = np.random.default_rng(3)
    lat, lon = 40 + rng.normal(0, 0.05, 50), -3.7 + rng.normal(0, 0.05, 50)
    l2 = np.sort(rng.uniform(0.5, 1.5, 50))
    bg = (40 + rng.normal(0, 2, 300), -3.7 + rng.normal(0, 2, 300), rng.uniform(1, 9, 300))
    prior = (40.01, -3.69)
    g = haversine_km(prior[0], prior[1], lat, lon)
    for model in (ErrorModel((5.0, 300.0), (0.6, 0.39), 0.01), MODEL):
        given = (dict(prior_km=g), dict(background=prior_weighted_background(bg, prior, model),
                                        background_weighted=True))
        for fixed in (None, 3):
            a = fuse(l2, lat, lon, 0.2, prior=prior, error_model=model, background=bg,
                     fixed_best=fixed)
            for extra in given:
                b = fuse(l2, lat, lon, 0.2, **{"prior": prior, "error_model": model,
                                               "background": bg, "fixed_best": fixed, **extra})
                assert np.array_equal(a.weights, b.weights)
                assert np.array_equal(a.votes, b.votes)
                assert (a.best, a.r68_m, a.r95_m) == (b.best, b.r68_m, b.r95_m)
                assert np.array_equal(a.extra["prior_km"], b.extra["prior_km"])


def test_a_repeated_prior_gets_the_same_submaps_and_answer_as_a_new_localizer():
    """The localizer keeps the last prior's submap choice and weighted background: a prior
    that repeats, another prior in between, or settings changed at run time give what a fresh
    localizer gives."""
    rng = np.random.default_rng(6)
    pos = np.concatenate([rng.normal((40.0, -3.7), 0.5, (150, 2)),
                          rng.normal((48.8, 2.3), 0.5, (150, 2))])
    desc = rng.normal(size=(300, 16)).astype(np.float32)
    m = assemble_map(desc, pos, [f"r{i}" for i in range(300)],
                     {"name": "synthetic", "dim": 16, "config": {}, "preprocessing": {}}, {},
                     "kmeans", clusters=6)
    queries = desc[:4] + 0.05 * rng.normal(size=(4, 16)).astype(np.float32)
    priors = [prior_at(40.1, -3.6), prior_at(40.1, -3.6), prior_at(48.7, 2.2, 30.0),
              prior_at(40.1, -3.6), prior_at(40.1, -3.6, 30.0)]
    for cfg in (LocalizerConfig(top_p=10), LocalizerConfig(top_p=10, fusion="paper"),
                LocalizerConfig(top_p=10, fusion="paper", n_submaps=2)):
        kept = Localizer(m, cfg)
        for q in queries:
            for pr in priors:
                fresh = Localizer(m, kept.config)
                assert kept.select_submaps(pr.prior) == fresh.select_submaps(pr.prior)
                a, b = kept.localize(q, pr), fresh.localize(q, pr)
                assert (a.lat, a.lon, a.ref_id, a.submap, a.uncertainty_m, a.radius95_m,
                        a.confidence, a.flags) == (b.lat, b.lon, b.ref_id, b.submap,
                                                   b.uncertainty_m, b.radius95_m,
                                                   b.confidence, b.flags)
                assert [c.posterior for c in a.candidates] == [c.posterior
                                                               for c in b.candidates]
        kept.config = LocalizerConfig(top_p=10, prior_quantile=0.5, fusion=cfg.fusion)
        pr = priors[0]
        assert kept.select_submaps(pr.prior) == Localizer(m, kept.config).select_submaps(
            pr.prior)
        chosen, _ = kept.select_submaps(pr.prior)
        chosen.append(-1)  # the caller's list is its own
        assert -1 not in kept.select_submaps(pr.prior)[0]
