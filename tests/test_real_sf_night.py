"""Real retrieval check on ../shared/data/sf_night (332 database + 34 night queries, most from
another date than their match); skipped when ../shared is absent. README reports the figure."""

import pytest

from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.mapping.coords_csv import read_coords_csv
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline


@pytest.fixture(scope="module")
def sf(sf_night_map):
    return sf_night_map


def test_sf_night_recall_within_25m(sf):
    root, map_dir = sf
    pipe = LocalizationPipeline.open(map_dir, localizer={"top_p": 5})
    queries = read_coords_csv(root / "queries.csv")
    assert len(queries) == 34
    r1 = r5 = 0
    for f, lat, lon in queries:
        hyp = pipe.localize_image(load_image(root / f), None)
        d_m = [haversine_km(lat, lon, c.lat, c.lon) * 1000 for c in hyp.candidates[:5]]
        r1 += d_m[0] <= 25
        r5 += min(d_m) <= 25
    recall1, recall5 = 100 * r1 / 34, 100 * r5 / 34
    print(f"sf_night vlad_rootsift: Recall@1 {recall1:.1f}%  Recall@5 {recall5:.1f}% (25 m)")
    # measured 50.0 / 55.9 on this machine; a broken descriptor gives ~0 (chance is < 2 %)
    assert recall1 >= 40.0 and recall5 >= 50.0


def test_sf_night_prior_restricts_to_submap(sf):
    root, map_dir = sf
    from vlm_vpr_ros.priors.provider import Prior, PriorResult

    pipe = LocalizationPipeline.open(map_dir, localizer={"fusion": "paper"})
    f, lat, lon = read_coords_csv(root / "queries.csv")[0]
    hyp = pipe.localize_image(load_image(root / f), PriorResult(Prior(lat, lon, "gt"), "gt"))
    sub = pipe.map.submaps[pipe.map.submap_index(hyp.submap)]
    assert {c.ref_id for c in hyp.candidates} <= set(sub.ids)
    assert haversine_km(lat, lon, hyp.lat, hyp.lon) < 5.0  # same city district at worst


# -- fusion targets (issue 9, docs/fusion.md) -----------------------------------------------------
CITY_CENTRE = (37.7749, -122.4194)  # a typical VLM answer for a San Francisco photo


@pytest.fixture(scope="module")
def sf_queries(sf_described):
    """Descriptors and ground truth of the 34 night queries (computed once)."""
    import numpy as np

    described, truth = sf_described
    return np.stack([q.desc for q in described]), truth


def _offset(lat, lon, km, bearing):
    import math

    from vlm_vpr_ros.geodesy import EARTH_RADIUS_KM

    d, la, lo = km / EARTH_RADIUS_KM, math.radians(lat), math.radians(lon)
    la2 = math.asin(math.sin(la) * math.cos(d) + math.cos(la) * math.sin(d) * math.cos(bearing))
    lo2 = lo + math.atan2(math.sin(bearing) * math.sin(d) * math.cos(la),
                          math.cos(d) - math.sin(la) * math.sin(la2))
    return math.degrees(la2), math.degrees(lo2)


def _run(ref_map, desc, truth, priors, fold=None, **cfg):
    """(R@1 within 25 m, coverage of the 68 % and 95 % radii, wrong-continent answers)."""
    from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
    from vlm_vpr_ros.priors.provider import Prior, PriorResult

    loc = Localizer(ref_map, LocalizerConfig(**cfg))
    hits = c68 = c95 = far = 0
    for d, (la, lo), p in zip(desc, truth, priors):
        pr = None if p is None else PriorResult(Prior(p[0], p[1], "test"), "test")
        h = loc.localize(d, pr)
        lat, lon = h.lat, h.lon
        if fold is not None and lat < 0:  # a look-alike answer, folded back to its original
            far += 1
            lat, lon = lat - fold[0], lon - fold[1]
        err_m = haversine_km(la, lo, lat, lon) * 1000
        hits += err_m <= 25
        e_m = haversine_km(la, lo, h.lat, h.lon) * 1000
        c68 += e_m <= h.uncertainty_m
        c95 += e_m <= h.radius95_m
    n = len(desc)
    return hits, 100 * c68 / n, 100 * c95 / n, far


def test_sf_night_fusion_never_loses_to_vpr_and_is_calibrated(sf, sf_queries):
    import math

    import numpy as np

    root, map_dir = sf
    desc, truth = sf_queries
    m = LocalizationPipeline.open(map_dir).map
    rng = np.random.default_rng(0)
    near = [_offset(la, lo, rng.uniform(0.5, 2.0), rng.uniform(0, 2 * math.pi))
            for la, lo in truth]
    n = len(desc)
    vpr = _run(m, desc, truth, [None] * n, fusion="paper")
    rows = {"VPR only (best descriptor match)": vpr,
            "posterior, no prior": _run(m, desc, truth, [None] * n)}
    for name, pri in (("city-centre prior", [CITY_CENTRE] * n), ("prior 0.5-2 km off", near)):
        rows[f"paper, {name}"] = _run(m, desc, truth, pri, fusion="paper")
        rows[f"posterior, {name}"] = _run(m, desc, truth, pri)
    print(f"\nsf_night fusion (top-p 50, {n} night queries; R@1 within 25 m; coverage of the "
          "calibrated radii)")
    for name, (hits, c68, c95, _) in rows.items():
        print(f"  {name:<36} R@1 {hits:2d}/{n} ({100 * hits / n:5.1f}%)  cov68 {c68:5.1f}%  "
              f"cov95 {c95:5.1f}%")
    for name in ("city-centre prior", "prior 0.5-2 km off"):
        fused, paper = rows[f"posterior, {name}"][0], rows[f"paper, {name}"][0]
        print(f"  {name}: fused {fused} vs VPR-only {vpr[0]} (target >= {vpr[0] - 1}); "
              f"vs paper {paper} (target >= 10x: {10 * paper})")
        assert fused >= vpr[0] - 1  # never loses to VPR alone
        assert fused >= 5 * max(paper, 1)  # paper mode: 0-2 hits; see docs/fusion.md
    # calibration (map leave-one-out only; the night queries are held out): all queries of
    # the three regimes pooled
    pooled = [rows[k] for k in ("posterior, no prior", "posterior, city-centre prior",
                                "posterior, prior 0.5-2 km off")]
    c68 = sum(r[1] for r in pooled) / 3
    c95 = sum(r[2] for r in pooled) / 3
    print(f"  coverage pooled over {3 * n} fused answers: 68 % radius {c68:.1f}% (target "
          f"55-80), 95 % radius {c95:.1f}% (target >= 88)")
    assert 55.0 <= c68 <= 80.0 and c95 >= 88.0


@pytest.fixture(scope="module")
def twin(sf, sf_queries, tmp_path_factory):
    """(twin map, SF map, SF -> Sydney shift, priors 0-25 km off the queries' truth): the SF
    database twice, true coordinates + look-alike copies (descriptors perturbed far below their
    spread) shifted to Sydney."""
    import math

    import numpy as np

    from vlm_vpr_ros.mapping.assemble import assemble_map
    from vlm_vpr_ros.mapping.build_images import write_map_calibration
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    _, map_dir = sf
    base = LocalizationPipeline.open(map_dir).map
    d0, c0, ids0 = base.all_descriptors(), base.all_coords(), base.all_ids()
    rng = np.random.default_rng(1)
    shift = (-33.8688 - 37.7577, 151.2093 + 122.4704 - 360.0)  # SF -> Sydney
    d0 = d0 + rng.normal(0, 1e-5, d0.shape).astype(np.float32)  # both copies perturbed alike:
    twin_desc = d0 + rng.normal(0, 1e-5, d0.shape).astype(np.float32)  # no bias to either
    twin = assemble_map(np.concatenate([d0, twin_desc]),
                        np.concatenate([c0, c0 + np.array(shift)]),
                        ids0 + [f"twin/{i}" for i in ids0], base.descriptor_identity,
                        base.descriptor_state, "kmeans", 16)
    out = tmp_path_factory.mktemp("twin") / "twin"
    twin.save(out)
    write_map_calibration(twin, np.concatenate([d0, twin_desc]),
                          np.concatenate([c0, c0 + np.array(shift)]))
    priors = [_offset(la, lo, rng.uniform(0.0, 25.0), rng.uniform(0, 2 * math.pi))
              for la, lo in sf_queries[1]]
    return ReferenceMap.load(out), base, shift, priors


def test_twin_city_prior_resolves_the_look_alikes(sf, sf_queries, sf_described, twin):
    """VPR alone cannot tell the twins apart; a prior up to 25 km off must."""
    desc, truth = sf_queries
    twin, base, shift, priors = twin
    n = len(desc)
    vpr_hits, _, _, vpr_far = _run(twin, desc, truth, [None] * n, fold=shift, fusion="paper")
    hits, c68, c95, far = _run(twin, desc, truth, priors, fold=shift)
    paper_hits, _, _, paper_far = _run(twin, desc, truth, priors, fold=shift, fusion="paper")
    print(f"\ntwin-city map ({twin.n_references} references, SF + look-alikes in Sydney), "
          f"{n} night queries, priors 0-25 km off:\n"
          f"  VPR only: wrong twin {vpr_far}/{n}, R@1 (25 m, look-alikes folded back) "
          f"{vpr_hits}/{n}\n"
          f"  paper   : wrong twin {paper_far}/{n}, R@1 {paper_hits}/{n}\n"
          f"  fused   : wrong twin {far}/{n}, R@1 {hits}/{n}, cov68 {c68:.1f}% "
          f"cov95 {c95:.1f}%")
    # VPR alone picks the wrong twin about half the time (binomial 34 x 0.5: 95 % in 11..23)
    assert vpr_far >= 11
    assert far <= 1  # the prior resolves the twin
    assert hits >= vpr_hits - 1
    _twin_verified(twin, base, sf_described, priors, hits, shift)


def _twin_verified(twin, base, sf_described, priors, fused_hits, shift):
    """The twin map with its features (the SF references' own, copied to the look-alikes) and
    its own leave-one-out calibration: a verified fix never lands on the wrong continent, and
    with a prior on the wrong continent there is none (the answer is prior_resolved)."""
    from vlm_vpr_ros.mapping.local_features import (ReferenceExtractor, calibrate_map,
                                                    store_features)
    from vlm_vpr_ros.maps.features import FeatureStore
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    store = FeatureStore.open(base.path, base.manifest)
    where = {i: (s.id, j) for s in base.submaps for j, i in enumerate(s.ids)}
    sf_pipe = LocalizationPipeline.open(base.path)
    store_features(twin, lambda i: store.get(*where[i.removeprefix("twin/")]),
                   ReferenceExtractor(sf_pipe.descriptor, "sift"))
    calibrate_map(twin, max_queries=150)
    pipe = LocalizationPipeline.open(twin.path)
    described, truth = sf_described
    n = len(truth)
    sydney = [(la + shift[0], (lo + shift[1] + 180.0) % 360.0 - 180.0)  # the wrong continent
              for la, lo in priors]
    rows = {}
    for name, pri in (("priors 0-25 km off", priors), ("priors on the wrong continent",
                                                        sydney)):
        res = _verified(pipe, described, truth, pri)
        wrong = sum(1 for r in res if r[1] == "fix" and r[5] < 0)
        fixes = sum(1 for r in res if r[1] == "fix")
        hits = 0
        for (la, lo), r in zip(truth, res):  # a look-alike answer folded back (as _run)
            fold = r[5] < 0
            hits += haversine_km(la, lo, r[5] - shift[0] * fold, r[6] - shift[1] * fold) \
                * 1000 <= 25
        rows[name] = (hits, fixes, wrong)
        print(f"  verified, {name}: R@1 {hits}/{n} (fused today {fused_hits}), fixes "
              f"{fixes}, on the wrong continent {wrong} (target 0)")
        assert wrong == 0
    assert rows["priors 0-25 km off"][0] >= fused_hits - 1
    assert rows["priors on the wrong continent"][1] == 0
    assert ReferenceMap.load(twin.path).manifest["local_features"]["n_keypoints"] == \
        2 * base.manifest["local_features"]["n_keypoints"]


def test_one_pass_retrieval_answers_as_two_searches(sf, sf_queries, twin):
    """Issue 23: the posterior's region + global top-p from one pass gives the same candidates
    (ids, distances, order) and the same answers as the two searches it replaced, on SF night
    and on the twin map, for wide (VLM-like) and tight (sigma 0.5 / 3 km) priors 0-25 km off."""
    import math

    import numpy as np
    from two_search import TwoSearchLocalizer, assert_same_answers

    from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
    from vlm_vpr_ros.priors.provider import Prior, PriorResult

    desc, truth = sf_queries
    rng = np.random.default_rng(2)
    off = [_offset(la, lo, rng.uniform(0.0, 25.0), rng.uniform(0, 2 * math.pi))
           for la, lo in truth]
    priors = [None if i % 7 == 6 else PriorResult(
        Prior(p[0], p[1], "test", (None, 0.5, 3.0)[i % 3]), "test") for i, p in enumerate(off)]
    merged = 0
    for ref_map in (LocalizationPipeline.open(sf[1]).map, twin[0]):
        for cfg in (LocalizerConfig(), LocalizerConfig(top_p=5),
                    LocalizerConfig(fusion="paper")):
            merged += assert_same_answers(Localizer(ref_map, cfg),
                                          TwoSearchLocalizer(ref_map, cfg), desc, priors)
    assert merged >= 40  # the tight priors' regions are a few submaps: the merge ran


# -- verified fixes (issue 18, docs/verification.md) ----------------------------------------------
def _verified(pipe, queries, truth, priors, cut=17):
    """Run the full pipeline (retrieval, fusion, verification, status) on precomputed query
    descriptions; per-answer (error m, status, sigma m, p_correct, covered by r68) and R@1."""
    from vlm_vpr_ros.localization.verification.status import horizontal_sigma
    from vlm_vpr_ros.priors.provider import Prior, PriorResult

    out = []
    for q, (la, lo), p in zip(queries, truth, priors):
        pr = None if p is None else PriorResult(Prior(p[0], p[1], "test"), "test")
        h = pipe.localize_descriptor(q.desc, pr, q.local)
        e = haversine_km(la, lo, h.lat, h.lon) * 1000
        out.append((e, h.status, horizontal_sigma(h), h.p_correct, e <= h.uncertainty_m,
                    h.lat, h.lon))
    return out


@pytest.fixture(scope="module")
def sf_described(sf):
    """The 34 night queries through describe_query (global descriptor + SIFT, one pass)."""
    import numpy as np

    root, map_dir = sf
    pipe = LocalizationPipeline.open(map_dir)
    queries = read_coords_csv(root / "queries.csv")
    return ([pipe.describe_query(load_image(root / f)) for f, _, _ in queries],
            np.array([[la, lo] for _, la, lo in queries]))


def test_sf_night_verified_fixes_are_right_and_radii_honest(sf, sf_described):
    """Targets of issue 18 on the 34 night queries; p_correct calibrated by leave-one-out on
    the 332 references only (no threshold chosen on these queries)."""
    import math

    import numpy as np

    root, map_dir = sf
    described, truth = sf_described
    pipe = LocalizationPipeline.open(map_dir)
    n = len(truth)
    rng = np.random.default_rng(0)
    near = [_offset(la, lo, rng.uniform(0.5, 2.0), rng.uniform(0, 2 * math.pi))
            for la, lo in truth]
    settings = {"no prior": [None] * n, "city-centre prior": [CITY_CENTRE] * n,
                "prior 0.5-2 km off": near}
    print(f"\nsf_night verified fixes ({n} night queries; halves = queries 1-17 / 18-34)")
    pooled = []
    for name, pri in settings.items():
        res = _verified(pipe, described, truth, pri)
        today = _run(pipe.map, [q.desc for q in described], truth, pri)[0]
        fixes = [r[0] for r in res if r[1] == "fix"]
        halves = [sum(1 for r in res[a:b] if r[1] == "fix") for a, b in ((0, 17), (17, n))]
        r1 = sum(r[0] <= 25 for r in res)
        print(f"  {name:<20} R@1 {r1}/{n} (today {today}); fixes {len(fixes)}/{n} "
              f"(halves {halves[0]} + {halves[1]}; issue 18 target >= 8 at 0.95), fix "
              f"errors m {sorted(round(e) for e in fixes)} (target all <= 50)")
        # issue 27: the default threshold is 0.99 (docs/verification.md section 2): 3 of the
        # former 9 fixes remain at full size (benchmarks/bench_integrity.py); none is wrong
        assert all(e <= 50 for e in fixes) and len(fixes) >= 2
        assert r1 >= today
        pooled += res
    cov = 100 * sum(r[4] for r in pooled) / len(pooled)
    fix_sigma = float(np.median([r[2] for r in pooled if r[1] == "fix"]))
    bad_sigma = float(np.median([r[2] for r in pooled if r[1] != "fix" and r[0] > 1000]))
    print(f"  68 % radius covers {cov:.1f}% of {len(pooled)} answers (target 55-85); median "
          f"sigma: fixes {fix_sigma:.1f} m, NO_FIX answers wrong by > 1 km {bad_sigma:.0f} m "
          f"(ratio {bad_sigma / fix_sigma:.0f}x, target >= 10x)")
    assert 55.0 <= cov <= 85.0 and bad_sigma >= 10 * fix_sigma
    # featureless frames on this map: never a fix
    from test_verification_maps import featureless_frames

    for name, frame in featureless_frames().items():
        h = pipe.localize_image(frame)
        assert h.status == "no_fix", (name, h.status_reason)


# -- integrity at robot resolutions (issue 27, docs/verification.md) ------------------------------
def test_sf_night_integrity_at_robot_resolutions(sf):
    """The 34 queries at full size, fitted inside 640x480 and 480x360 and JPEG q40 at 640x480,
    no prior and a city-centre prior, on the map as built (leave-one-out over the four
    conditions on its references only): no fix more than 50 m off and no fix whose error exceeds
    its protection level (HMI); protection levels of fixes median <= 40 m."""
    import statistics

    from vlm_vpr_ros.localization.verification.conditions import parse_condition
    from vlm_vpr_ros.priors.provider import Prior, PriorResult

    root, map_dir = sf
    pipe = LocalizationPipeline.open(map_dir)
    assert len(pipe.verifier.model.conditions) == 4
    queries = read_coords_csv(root / "queries.csv")
    pls, counts = [], {}
    for cname in ("full", "fit640x480", "fit480x360", "jpeg40_640x480"):
        cond = parse_condition(cname)
        described = [(pipe.describe_query(cond.apply(load_image(root / f))), la, lo)
                     for f, la, lo in queries]
        for pname, prior in (("no prior", None), ("city-centre prior", CITY_CENTRE)):
            fixes = []
            for q, la, lo in described:
                pr = None if prior is None else PriorResult(Prior(*prior, "test"), "test")
                h = pipe.localize_descriptor(q.desc, pr, q.local)
                if h.status == "fix":
                    fixes.append((haversine_km(la, lo, h.lat, h.lon) * 1000, h.protection_m))
            bad = sum(e > 50 for e, _ in fixes)
            hmi = sum(e > pl for e, pl in fixes)
            counts[cname, pname] = len(fixes)
            pls += [pl for _, pl in fixes]
            print(f"  {cname:<15} {pname:<18} fixes {len(fixes):2d}, > 50 m off {bad}, HMI {hmi}")
            assert bad == 0 and hmi == 0, (cname, pname, fixes)
    print(f"  median protection level of fixes {statistics.median(pls):.1f} m (target <= 40)")
    assert statistics.median(pls) <= 40.0
    # availability: measured 3 at full size and 3 at 640x480 (targets 8 / 7 not met at 0.99;
    # docs/verification.md section 7)
    assert counts["full", "no prior"] >= 2 and counts["fit640x480", "no prior"] >= 2


# -- issue 29: the robot's own estimate as a trusted prior (moved here from its own file: one
# SF map per run, the module's, whatever worker runs it) --------------------------------------
@pytest.mark.timeout(3000)
def test_robot_prior_fixes_and_the_guard_against_a_lying_sigma(sf, tmp_path):
    """Offline through ``vlm-vpr localize --prior recorded`` with a ``sigma_m`` column
    (benchmarks/robot_prior_sf_night.py): an honest prior (truth moved 100 m, sigma_m 100)
    gives more fixes than no prior, none more than 50 m off; a prior that lies about its sigma
    (truth moved 2 km, still claiming 100 m) creates no wrong fix."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from robot_prior_sf_night import run

    data, map_dir = sf
    res = run(data, map_dir, tmp_path / "work")
    print(f"\nSF night robot prior: {res}")
    none, honest, lying = res["none"], res["honest"], res["lying"]
    assert none["off_50m"] == honest["off_50m"] == lying["off_50m"] == 0
    # the target of issue 29 is >= 15; measured 11 under the integrity rule (docs/node.md says
    # why the rest is held back): the honest prior must add fixes, never wrong ones
    assert honest["fixes"] >= none["fixes"] + 4
    assert lying["fixes"] <= none["fixes"]
