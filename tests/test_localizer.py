"""Localizer: FAISS retrieval vs NumPy brute force, re-rank, submap choice, flags, uncertainty."""

import math

import numpy as np
import pytest

from vlm_vpr_ros.errors import ConfigError, DescriptorError
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
from vlm_vpr_ros.mapping.assemble import assemble_map
from vlm_vpr_ros.priors.provider import Prior, PriorResult

# real cities (lat, lon) → clusters of references around them
CITIES = {"paris": (48.8566, 2.3522), "tokyo": (35.6762, 139.6503),
          "nairobi": (-1.2921, 36.8219), "lima": (-12.0464, -77.0428)}


def synthetic_map(method="kmeans", clusters=4, n_per=40, dim=32, seed=0):
    rng = np.random.default_rng(seed)
    coords, ids = [], []
    for name, (la, lo) in CITIES.items():
        for i in range(n_per):
            coords.append((la + rng.normal(0, 0.05), lo + rng.normal(0, 0.05)))
            ids.append(f"{name}_{i:03d}.jpg")
    desc = rng.normal(size=(len(ids), dim)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    ident = {"name": "synthetic", "dim": dim, "config": {}, "preprocessing": {}}
    return assemble_map(desc, np.array(coords), ids, ident, {}, method, clusters), desc, ids


def prior_at(lat, lon):
    return PriorResult(Prior(lat, lon, "test"), "test")


def brute_force(desc_db, q, rows, k):
    d = ((desc_db[rows] - q) ** 2).sum(1)
    order = np.argsort(d, kind="stable")[:k]
    return [rows[i] for i in order], d[order]


def test_search_equals_numpy_brute_force_global_and_submap():
    m, desc, ids = synthetic_map()
    loc = Localizer(m, LocalizerConfig(top_p=15))
    rng = np.random.default_rng(1)
    for _ in range(10):
        q = rng.normal(size=desc.shape[1]).astype(np.float32)
        cands = loc.search(q, list(range(len(m.submaps))), 15)
        ref_rows, ref_d = brute_force(desc, q, np.arange(len(ids)), 15)
        assert [c.ref_id for c in cands] == [ids[i] for i in ref_rows]
        np.testing.assert_allclose([c.l2_sq for c in cands], ref_d, rtol=1e-4, atol=1e-5)
        # one submap: only its members, same order as brute force over them
        sub = m.submaps[0]
        rows = np.array([ids.index(i) for i in sub.ids])
        cands = loc.search(q, [0], 7)
        sub_rows, _ = brute_force(desc, q, rows, 7)
        assert [c.ref_id for c in cands] == [ids[i] for i in sub_rows]


@pytest.mark.parametrize("saved", [False, True])
@pytest.mark.parametrize("per_submap", [1, 10 ** 6])
def test_retrieved_arrays_are_the_hits_positions_and_ids(tmp_path, monkeypatch, saved,
                                                         per_submap):
    """What localize() fuses (``Localizer.retrieve``: a read per submap, or per hit when the
    hits are spread) equals reading each hit's id, position and submap one by one, in memory
    and from a saved (memory-mapped) map, for one submap, several, and with the global merge;
    ``search`` gives the same candidates."""
    from vlm_vpr_ros.localization import localizer
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    monkeypatch.setattr(localizer, "READS_PER_SUBMAP", per_submap)

    m, desc, _ = synthetic_map(clusters=4)
    if saved:
        m.save(tmp_path / "map")
        m = ReferenceMap.load(tmp_path / "map")
    loc = Localizer(m, LocalizerConfig(top_p=30))
    rng = np.random.default_rng(4)
    everything = list(range(len(m.submaps)))
    for sets, with_global in (([0], False), ([1, 3], False), (everything, False), ([2], True)):
        q = rng.normal(size=desc.shape[1]).astype(np.float32)
        got = loc.retrieve(q, sets, 30, with_global)
        dist, sub, row = m.rank_submaps(sets, q[None, :], 30, with_global)
        assert len(got) == len(dist) > 0
        assert got.l2_sq.tolist() == dist.tolist() and got.rows.tolist() == row.tolist()
        for i, (si, j) in enumerate(zip(sub.tolist(), row.tolist())):
            s = m.submaps[si]
            assert got.ref_ids[i] == s.ids[j] and got.submaps[i] == s.id
            assert (got.lat[i], got.lon[i]) == (float(s.coords[j, 0]), float(s.coords[j, 1]))
        cands = loc.search(q, sets, 30, with_global)
        assert [(c.ref_id, c.lat, c.lon, c.l2_sq, c.submap, c.row) for c in cands] == list(zip(
            got.ref_ids, got.lat.tolist(), got.lon.tolist(), got.l2_sq.tolist(), got.submaps,
            got.rows.tolist()))


def test_rerank_chooses_nearest_candidate_to_prior():
    m, desc, ids = synthetic_map()
    loc = Localizer(m, LocalizerConfig(top_p=50, use_submaps=False, fusion="paper"))
    q = desc[ids.index("tokyo_003.jpg")] + 0.01
    prior = prior_at(*CITIES["lima"])
    hyp = loc.localize(q, prior)
    # independent check: the candidate set is the brute-force top-50; pick min distance to prior
    rows, _ = brute_force(desc, q, np.arange(len(ids)), 50)
    coords = np.concatenate([s.coords for s in m.submaps])
    all_ids = [i for s in m.submaps for i in s.ids]
    cc = np.array([coords[all_ids.index(ids[r])] for r in rows])
    best = rows[int(np.argmin(haversine_km(*CITIES["lima"], cc[:, 0], cc[:, 1])))]
    assert hyp.ref_id == ids[best] and hyp.ref_id.startswith("lima")
    assert hyp.candidates[0].prior_km <= hyp.candidates[-1].prior_km
    assert hyp.submap == "*" and "no_submap" in hyp.flags


def test_ranked_candidates_follow_each_modes_keys_and_are_plain_candidates():
    """After the chosen one, the candidates are ordered by the mode's keys (recomputed here
    with Python's stable sort of the returned candidates): paper with a prior by (distance to
    the prior, descriptor distance), paper without one by descriptor distance, posterior by
    weight; Candidate.from_columns makes what the constructor makes (frozen, equal, hash)."""
    import dataclasses

    from vlm_vpr_ros.types import Candidate

    m, desc, ids = synthetic_map()
    q = desc[ids.index("tokyo_003.jpg")] + 0.01
    for fusion, prior, key in (("paper", prior_at(*CITIES["lima"]),
                                lambda c: (c.prior_km, c.l2_sq)),
                               ("paper", None, lambda c: c.l2_sq),
                               ("posterior", prior_at(*CITIES["tokyo"]), lambda c: -c.posterior)):
        hyp = Localizer(m, LocalizerConfig(top_p=30, use_submaps=False, fusion=fusion)).localize(
            q, prior)
        rest = hyp.candidates[1:]
        assert len(rest) == 29 and rest == sorted(rest, key=key), fusion
    cols = (["a", "b"], [1.0, 2.0], [3.0, 4.0], [0.5, 0.25], ["s0", "s1"], [None, 7.0],
            [0.9, None], [4, 5])
    fast = Candidate.from_columns(*cols)
    slow = [Candidate(*row) for row in zip(*cols)]
    assert fast == slow and [repr(c) for c in fast] == [repr(c) for c in slow]
    assert hash(fast[1]) == hash(slow[1]) and fast[0].inliers == -1
    with pytest.raises(dataclasses.FrozenInstanceError):
        fast[0].lat = 0.0
    with pytest.raises(ValueError):
        Candidate.from_columns(*cols[:-1], [4])


def test_no_rerank_keeps_best_descriptor_match():
    m, desc, ids = synthetic_map()
    q = desc[ids.index("tokyo_003.jpg")]
    hyp = Localizer(m, LocalizerConfig(rerank=False, use_submaps=False)).localize(
        q, prior_at(*CITIES["lima"]))
    assert hyp.ref_id == "tokyo_003.jpg" and "no_rerank" in hyp.flags
    assert "prior_far_from_match" in hyp.flags  # Tokyo is > 2500 km from Lima


def test_prior_selects_submap_kmeans():
    m, desc, ids = synthetic_map()
    q = desc[ids.index("tokyo_003.jpg")]
    hyp = Localizer(m, LocalizerConfig(fusion="paper")).localize(q, prior_at(48.0, 3.0))
    assert hyp.ref_id.startswith("paris")
    assert all(c.ref_id.startswith("paris") for c in hyp.candidates)
    assert hyp.submap in {s.id for s in m.submaps} and not hyp.flagged


def test_n_submaps_widens_search():
    m, desc, ids = synthetic_map()
    q = desc[ids.index("tokyo_003.jpg")]
    hyp = Localizer(m, LocalizerConfig(n_submaps=2, rerank=False, fusion="paper")).localize(
        q, prior_at(20.0, 90.0))  # between Tokyo and Nairobi, nearer Tokyo
    assert "+" in hyp.submap and len(hyp.submap.split("+")) == 2
    assert hyp.ref_id == "tokyo_003.jpg"


def test_country_submap_and_prior_outside_map():
    m, desc, ids = synthetic_map(method="country")
    assert {s.id for s in m.submaps} == {"FR", "JP", "KE", "PE"}
    q = desc[ids.index("paris_001.jpg")]
    paper = Localizer(m, LocalizerConfig(fusion="paper"))
    hyp = paper.localize(q, prior_at(43.6, 1.44))  # Toulouse, France
    assert hyp.submap == "FR" and hyp.ref_id.startswith("paris")
    hyp = paper.localize(q, prior_at(52.52, 13.405))  # Berlin: no German submap
    assert "prior_not_in_map" in hyp.flags and hyp.submap == "FR"  # nearest centroid


def test_no_prior_is_flagged_global_and_failed_prior_flagged():
    m, desc, ids = synthetic_map()
    q = desc[ids.index("nairobi_010.jpg")]
    hyp = Localizer(m).localize(q, None)
    assert hyp.ref_id == "nairobi_010.jpg" and hyp.flagged
    assert set(hyp.flags) == {"no_prior", "global"} and hyp.submap == "*"
    hyp = Localizer(m).localize(q, PriorResult.failure("openai:x", "timeout"))
    assert "prior_failed" in hyp.flags and hyp.ref_id == "nairobi_010.jpg"


def test_radii_are_finite_ordered_and_honest():
    m, desc, ids = synthetic_map()
    for fusion in ("posterior", "paper"):
        loc = Localizer(m, LocalizerConfig(use_submaps=False, fusion=fusion))
        rng = np.random.default_rng(3)
        for _ in range(20):
            q = rng.normal(size=desc.shape[1]).astype(np.float32)
            la, lo = rng.uniform(-60, 60), rng.uniform(-180, 180)
            hyp = loc.localize(q, prior_at(la, lo))
            assert math.isfinite(hyp.uncertainty_m) and hyp.uncertainty_m >= 25.0
            assert hyp.uncertainty_m <= hyp.radius95_m <= math.pi * 6371.0088e3
            assert hyp.fusion == fusion
            assert sum(c.posterior for c in hyp.candidates) == pytest.approx(1.0)
    # an exact, distinctive match with an agreeing prior is confident
    loc = Localizer(m, LocalizerConfig(use_submaps=False))
    q = desc[ids.index("lima_005.jpg")]
    hyp = loc.localize(q, prior_at(*CITIES["lima"]))
    assert hyp.ref_id == "lima_005.jpg" and hyp.uncertainty_m < 20_000
    assert hyp.confidence > 0.5
    # a random descriptor (no real match) with no prior is spread over the map: huge radius
    q = np.random.default_rng(9).normal(size=desc.shape[1]).astype(np.float32)
    assert loc.localize(q, None).radius95_m > 1_000_000


def test_dimension_mismatch_and_bad_config():
    m, desc, ids = synthetic_map()
    with pytest.raises(DescriptorError, match="dim 16"):
        Localizer(m).localize(np.zeros(16, np.float32), None)
    with pytest.raises(ConfigError):
        LocalizerConfig(top_p=0)


def test_fp16_index_equals_brute_force_on_rounded_descriptors(tmp_path):
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    rng = np.random.default_rng(5)
    desc = rng.normal(size=(300, 24)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    coords = np.stack([rng.uniform(-50, 50, 300), rng.uniform(-170, 170, 300)], 1)
    ids = [f"r{i}" for i in range(300)]
    ident = {"name": "synthetic", "dim": 24, "config": {}, "preprocessing": {}}
    m = assemble_map(desc, coords, ids, ident, {}, "kmeans", 5, index="fp16")
    m.save(tmp_path / "m")
    m = ReferenceMap.load(tmp_path / "m")
    assert m.manifest["index"] == "fp16"
    loc = Localizer(m)
    rounded = desc.astype(np.float16).astype(np.float32)
    for _ in range(5):
        q = rng.normal(size=24).astype(np.float32)
        got = loc.search(q, list(range(len(m.submaps))), 20)
        ref_rows, ref_d = brute_force(rounded, q, np.arange(300), 20)
        assert [c.ref_id for c in got] == [ids[i] for i in ref_rows]
        np.testing.assert_allclose([c.l2_sq for c in got], ref_d, rtol=1e-3, atol=1e-4)
