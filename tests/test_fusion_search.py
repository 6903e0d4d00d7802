"""One pass over the map for the posterior's region + global top-p (issue 23): the same candidates
in the same order and the same answers as the two searches it replaced (tests/two_search.py), on
maps with many submaps of every index kind, empty submaps, k above a submap's size and exact
ties; and every submap is searched once per query."""

from __future__ import annotations

import numpy as np
import pytest
from two_search import (TwoSearchLocalizer, assert_same_answers, search_submaps_v1,
                        two_searches_v1)

from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
from vlm_vpr_ros.mapping.assemble import assemble_map
from vlm_vpr_ros.maps.indexes import make_index
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.maps.submap import Submap
from vlm_vpr_ros.priors.provider import Prior, PriorResult

TOWNS = [(48.86, 2.35), (52.52, 13.40), (40.42, -3.70), (35.68, 139.65), (-33.87, 151.21),
         (40.71, -74.01), (34.05, -118.24), (-23.55, -46.63), (-1.29, 36.82), (28.61, 77.21)]
DIM = 24


def tied_map(kind: str, n: int, clusters: int, seed: int = 0, max_submap_size=None,
             clump: int = 0):
    """References around ten towns; a tenth of them are exact copies of other references (in
    the same and in other submaps), so distances tie; ``clump`` more share one descriptor
    (``copies[0, 0]``'s: more ties than a pq pool keeps); plus two empty submaps."""
    rng = np.random.default_rng(seed)
    town = rng.integers(0, len(TOWNS), n)
    coords = np.array(TOWNS)[town] + rng.normal(0, 0.3, (n, 2))
    desc = rng.normal(size=(n, DIM)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    copies = rng.choice(n, size=(n // 10, 2), replace=False)
    desc[copies[:, 1]] = desc[copies[:, 0]]
    desc[rng.choice(n, clump, replace=False)] = desc[copies[0, 0]]
    ident = {"name": "synthetic", "dim": DIM, "config": {}, "preprocessing": {}}
    m = assemble_map(desc, coords, [f"r{i}" for i in range(n)], ident, {}, "kmeans",
                     clusters, seed=seed, index=kind, max_submap_size=max_submap_size)
    for name, k in (("empty_a", "flat"), ("empty_b", "fp16")):
        m.submaps.append(Submap(name, (0.0, -30.0), np.zeros((0, 2)), [],
                                make_index(k, np.zeros((0, DIM), np.float32)), kind=k))
    m = ReferenceMap(m.manifest, m.submaps, {})
    return m, desc, copies


def queries_and_priors(desc, copies, rng, n=12):
    """Queries: copied references (ties at the top), references + noise, random vectors;
    priors: VLM-like (pooled error model), sigma 25 / 300 km, one far from every town, none."""
    q = np.concatenate([desc[copies[:4, 0]], desc[rng.integers(0, len(desc), 4)]
                        + rng.normal(0, 0.05, (4, DIM)).astype(np.float32),
                        rng.normal(size=(n - 8, DIM)).astype(np.float32)])
    priors = []
    for i in range(n):
        la, lo = TOWNS[i % len(TOWNS)]
        priors.append([PriorResult(Prior(la + 1.0, lo - 1.0, "test"), "test"),
                       PriorResult(Prior(la, lo, "test", 25.0), "test"),
                       PriorResult(Prior(la, lo, "test", 300.0), "test"),
                       PriorResult(Prior(-50.0, -140.0, "test", 25.0), "test"),
                       None][i % 5])
    return q, priors


@pytest.fixture(scope="module")
def maps():
    """flat, fp16 with ~40 submaps; pq (balanced: many pq submaps) and a mixed pq/fp16 map."""
    return {"flat": tied_map("flat", 1500, 40), "fp16": tied_map("fp16", 1500, 40, seed=1),
            "pq": tied_map("pq", 15000, 5, seed=2, max_submap_size=2000, clump=3000),
            "pq+fp16": tied_map("pq", 6000, 8, seed=3)}


@pytest.mark.parametrize("kind", ["flat", "fp16", "pq", "pq+fp16"])
def test_one_pass_answers_as_the_two_searches(maps, kind):
    m, desc, copies = maps[kind]
    kinds = {s.kind for s in m.submaps if s.count}
    assert kinds == {"flat": {"flat"}, "fp16": {"fp16"}, "pq": {"pq"},
                     "pq+fp16": {"pq", "fp16"}}[kind]
    assert len(m.submaps) >= 10 and min(s.count for s in m.submaps) == 0
    rng = np.random.default_rng(4)
    q, priors = queries_and_priors(desc, copies, rng)
    merged = 0
    for cfg in (dict(top_p=50), dict(top_p=7), dict(top_p=400),  # 400 > every flat submap
                dict(top_p=50, prior_quantile=0.5), dict(top_p=50, fusion="paper")):
        config = LocalizerConfig(**cfg)
        merged += assert_same_answers(Localizer(m, config), TwoSearchLocalizer(m, config),
                                      q, priors)
    assert merged >= 10  # the region + global merge was exercised


@pytest.mark.parametrize("kind", ["flat", "pq", "pq+fp16"])
def test_any_submap_set_in_any_order(maps, kind):
    """Arbitrary sets (the pq pool picks in the set's order), with and without the global
    merge, k from 1 to above the largest submap."""
    m, desc, copies = maps[kind]
    rng = np.random.default_rng(5)
    n_sub = len(m.submaps)
    for t in range(16):
        region = [int(i) for i in rng.permutation(n_sub)[:rng.integers(1, n_sub)]]
        k = int(rng.choice([1, 3, 50, 2000]))
        qv = (desc[copies[t // 2, 0]] if t % 2 == 0 else rng.normal(size=DIM)).astype(
            np.float32)  # t = 0: the clump's descriptor
        q = np.ascontiguousarray(qv[None, :])
        assert m.search_submaps(region, q, k) == search_submaps_v1(m, region, q, k)
        assert m.search_submaps(region, q, k, True) == two_searches_v1(m, region, q, k)


@pytest.mark.parametrize("kind", ["flat", "pq+fp16"])
def test_loaded_map_same_answers_each_submap_searched_once(maps, kind, tmp_path, monkeypatch):
    """A saved + memory-mapped (v2) map answers as the two searches; one query's merged search
    scans every live submap once (alone, or in the small submaps' pool, searched once) and
    re-ranks every pq row at most once."""
    m, desc, copies = maps[kind]
    m.save(tmp_path / "map")
    loaded = ReferenceMap.load(tmp_path / "map")
    rng = np.random.default_rng(6)
    q, priors = queries_and_priors(desc, copies, rng, n=10)
    assert assert_same_answers(Localizer(loaded), TwoSearchLocalizer(loaded), q, priors) >= 3
    calls: dict[str, list] = {"search": [], "pq": [], "rows": [], "pool": []}
    for s in loaded.submaps:
        for name, key in (("search", "search"), ("searchable", "search"),
                          ("pq_candidates", "pq"), ("exact_sq_l2", "rows")):
            orig = getattr(s, name)

            def spy(*a, _orig=orig, _key=key, _sid=s.id):
                calls[_key].append((_sid, a[0]) if _key == "rows" else _sid)
                return _orig(*a)
            monkeypatch.setattr(s, name, spy)
    small = loaded.small_submaps()
    pool_hits = small.hits
    monkeypatch.setattr(small, "hits", lambda *a: calls["pool"].append(1) or pool_hits(*a))
    pooled = [s.id for s, p in zip(loaded.submaps, small.pooled) if p]
    assert (len(pooled) > 10) == (kind == "flat")
    loc = Localizer(loaded)
    hyp = loc.localize(q[0], PriorResult(Prior(*TOWNS[0], "test", 25.0), "test"))
    region, _ = loc.select_submaps(hyp.prior)
    live = [s.id for s in loaded.submaps if s.count]
    assert hyp.submap == "*" and len(region) < len(live)
    searched = calls["search"] + calls["pq"]
    assert len(calls["pool"]) == (1 if pooled else 0)
    assert sorted(searched + pooled) == sorted(live)
    rows = [(sid, int(r)) for sid, rr in calls["rows"] for r in rr]
    assert len(rows) == len(set(rows)) and (kind == "flat" or rows)


@pytest.mark.parametrize("kind", ["flat", "fp16"])
def test_pooled_small_submaps_give_each_submaps_own_distances(kind, monkeypatch):
    """One call over the pooled copy returns, for every row of every small submap, the
    distance that submap's own FAISS search gives (dims with special FAISS kernels included);
    a pool over its byte limit keeps the smallest submaps and searches the rest alone."""
    from vlm_vpr_ros.maps import search

    rng = np.random.default_rng(8)
    for dim in (8, 12, 33, 128):
        subs = [Submap(f"s{i}", (0.0, 0.0), np.zeros((n, 2)), [f"r{j}" for j in range(n)],
                       make_index(kind, rng.normal(size=(n, dim)).astype(np.float32)),
                       kind=kind)
                for i, n in enumerate([1, 5, 40, search.POOL_MAX_REFS + 1, 256, 0, 17])]
        small = search.SmallSubmaps(subs)
        assert small.pooled.tolist() == [True, True, True, False, True, False, True]
        q = rng.normal(size=(1, dim)).astype(np.float32)
        d, s, r = small.hits(q)
        assert len(d) == 1 + 5 + 40 + 256 + 17
        for si in np.flatnonzero(small.pooled):
            want_d, want_r = subs[si].search(q, subs[si].count, 1)
            got = dict(zip(r[s == si].tolist(), d[s == si].tolist()))
            assert got == dict(zip(want_r.tolist(), want_d.tolist()))
    monkeypatch.setattr(search, "POOL_MAX_BYTES", (1 + 5 + 17) * 128 * (4 if kind == "flat"
                                                                         else 2))
    small = search.SmallSubmaps(subs)
    assert small.pooled.tolist() == [True, True, False, False, False, False, True]
    if kind == "fp16":  # fp16 is searched for all its rows: a cap in references too
        monkeypatch.setattr(search, "POOL_MAX_BYTES", 2 ** 30)
        monkeypatch.setattr(search, "POOL_MAX_FP16_REFS", 1 + 5 + 17)
        assert search.SmallSubmaps(subs).pooled.tolist() == [True, True, False, False, False,
                                                             False, True]


def test_pooled_flat_rows_in_huge_pages_search_as_an_index():
    """The flat pool's rows live in huge-page memory (2 MiB aligned, advised ``hg`` where the
    kernel has the advice) and are range-searched with the kernel of ``IndexFlatL2``: the same
    distances and rows as an index over the same rows, at the radius boundary too; a pool of
    several MB equals each submap's own search."""
    import mmap
    import os

    from vlm_vpr_ros.errors import MapError
    from vlm_vpr_ros.maps import search
    from vlm_vpr_ros.maps.indexes import range_search_rows
    from vlm_vpr_ros.maps.mapped import HUGE_PAGE_BYTES, huge_page_array

    THP = "/sys/kernel/mm/transparent_hugepage/enabled"
    small_arr = huge_page_array((3, 4), np.float32)  # under one huge page: plain memory
    assert small_arr.shape == (3, 4) and not small_arr.any()
    rng = np.random.default_rng(12)
    dim, sizes = 128, [900, 1000, 1100, 1200, 800]  # 20 MB of float32 rows
    subs = [Submap(f"s{i}", (0.0, 0.0), np.zeros((n, 2)), [f"r{j}" for j in range(n)],
                   make_index("flat", rng.normal(size=(n, dim)).astype(np.float32)))
            for i, n in enumerate(sizes)]
    pool = search.SmallSubmaps(subs)
    (kind, rows, owner, row), = pool.parts
    assert kind == "flat" and rows.dtype == np.float32 and rows.shape == (sum(sizes), dim)
    assert rows.flags.c_contiguous and rows.flags.writeable
    if hasattr(mmap, "MADV_HUGEPAGE") and os.path.exists(THP):  # a kernel with THP
        assert rows.ctypes.data % HUGE_PAGE_BYTES == 0
        start = rows.ctypes.data
        with open("/proc/self/smaps") as f:
            vmas = f.read().split("\n")
        for i, line in enumerate(vmas):  # the mapping holding the rows is advised "hg"
            lo, _, hi = line.partition(" ")[0].partition("-")
            if hi and all(c in "0123456789abcdef" for c in lo + hi) \
                    and int(lo, 16) <= start < int(hi, 16):
                flags = next(v for v in vmas[i:] if v.startswith("VmFlags:"))
                assert " hg" in flags
                break
        else:
            pytest.fail("the pool's mapping is not in /proc/self/smaps")
    index = make_index("flat", rows)
    q = rng.normal(size=(1, dim)).astype(np.float32)
    _, all_d, _ = index.range_search(q, np.float32(np.inf))
    radius = float(np.sort(all_d)[40])  # a distance that occurs: the boundary is exclusive
    _, want_d, want_r = index.range_search(q, radius)
    got_d, got_r = range_search_rows(rows, q, radius)
    assert np.array_equal(got_d, want_d) and np.array_equal(got_r, want_r) and len(got_r) == 40
    d, s, r = pool.hits(q)
    for si, sub in enumerate(subs):
        want_d, want_r = sub.search(q, sub.count, 1)
        assert dict(zip(r[s == si].tolist(), d[s == si].tolist())) == dict(
            zip(want_r.tolist(), want_d.tolist()))
    for bad in (rows.astype(np.float64), rows[:, :-1], np.asfortranarray(rows[:100])):
        with pytest.raises(MapError):
            range_search_rows(bad, q, radius)


@pytest.mark.parametrize("kind", ["flat", "fp16"])
def test_back_to_back_searches_are_each_indexs_own_search(kind):
    """The pass's flat/fp16 searches called back to back give what each index's own FAISS
    search gives (k below, at and — refused — above a submap's size; odd dims)."""
    from vlm_vpr_ros.errors import MapError
    from vlm_vpr_ros.maps.indexes import search_exact_many

    rng = np.random.default_rng(9)
    for dim in (12, 33, 128):
        idx = [make_index(kind, rng.normal(size=(n, dim)).astype(np.float32))
               for n in (1, 7, 300, 2000)]
        q = rng.normal(size=(1, dim)).astype(np.float32)
        ks = [1, 7, 50, 400]
        dist, at, rows = search_exact_many(list(zip(idx, ks)), q)
        assert np.array_equal(at, np.repeat(np.arange(len(idx)), ks))  # in found's order
        for i, (index, k) in enumerate(zip(idx, ks)):
            d, r = dist[at == i], rows[at == i]
            want_d, want_r = index.search(q, k)  # FAISS's own Python search
            assert np.array_equal(d, want_d[0]) and np.array_equal(r, want_r[0])
            assert d.dtype == np.float32 and r.dtype == np.int64
        nan = search_exact_many(list(zip(idx, ks)), np.full((1, dim), np.nan, np.float32))
        assert all(len(a) == 0 for a in nan)  # no distance enters FAISS's heap: no hits
        with pytest.raises(MapError):
            search_exact_many([(idx[1], 8)], q)
        with pytest.raises(MapError):
            search_exact_many([(idx[1], 3)], q[:, :-1])
    assert all(len(a) == 0 for a in search_exact_many([], q))


@pytest.mark.parametrize("kind", ["flat", "fp16"])
def test_without_the_pool_the_back_to_back_pass_answers_as_the_two_searches(kind,
                                                                           monkeypatch):
    """Every submap searched alone (no pool): the pass's back-to-back searches give the
    answers of the pre-issue-23 two searches, and each live submap is searched once."""
    from vlm_vpr_ros.maps import search

    monkeypatch.setattr(search, "POOL_MAX_REFS", 0)
    m, desc, copies = tied_map(kind, 1500, 12, seed=4)
    assert not m.small_submaps().pooled.any()
    rng = np.random.default_rng(10)
    q, priors = queries_and_priors(desc, copies, rng, n=10)
    for cfg in (dict(top_p=50), dict(top_p=400), dict(top_p=50, fusion="paper", n_submaps=3)):
        config = LocalizerConfig(**cfg)
        assert_same_answers(Localizer(m, config), TwoSearchLocalizer(m, config), q, priors)
    calls: list[str] = []
    for s in m.submaps:
        orig = s.searchable
        monkeypatch.setattr(s, "searchable", lambda _o=orig, _id=s.id: calls.append(_id) or _o())
    Localizer(m).localize(q[0], priors[1])  # sigma 25 km: region + global merge
    assert sorted(calls) == sorted(s.id for s in m.submaps if s.count)


def test_rerank_distances_are_exact_float32_distances_to_the_fp16_vectors(monkeypatch):
    """The pq re-rank (OpenCV, or FAISS's fp16 decoder on one OpenMP thread in a query) gives
    the exact float32 distances to the fp16 vectors, bit for bit, for odd and even dims, in
    fresh arrays (a few rows) or this thread's buffers (one block of rows or several, after
    calls of other sizes, and another thread's); rows outside the vectors are an error."""
    import threading

    from vlm_vpr_ros.maps import indexes
    from vlm_vpr_ros.maps.indexes import exact_sq_l2
    from vlm_vpr_ros.maps.search import one_faiss_thread

    rng = np.random.default_rng(7)
    for dim, n, k, block_bytes in ((24, 300, 120, None), (33, 300, 120, None),
                                   (512, 300, 120, None), (512, 3000, 1001, None),
                                   (512, 3000, 1001, 64 * 2048),  # 64 rows: several blocks
                                   (96, 3000, 2000, 384 * 300),  # a partial last block
                                   (64, 300, 260, None),  # buffers reused, after larger calls
                                   (24, 300, 7, None)):  # a few rows: fresh arrays
        half = (rng.normal(size=(n, dim)) * rng.uniform(0.01, 100)).astype(np.float16)
        rows = np.sort(rng.choice(n, k, replace=False))
        q = rng.normal(size=(1, dim)).astype(np.float32)
        want = half[rows].astype(np.float32) - q  # fp16 -> float32 is exact
        want = np.einsum("ij,ij->i", want, want)
        with monkeypatch.context() as m:
            if block_bytes:
                m.setattr(indexes, "RERANK_BLOCK_BYTES", block_bytes)
            with one_faiss_thread():
                got = exact_sq_l2(half, rows, q)
            assert got.dtype == np.float32 and np.array_equal(got, want)
            assert np.array_equal(exact_sq_l2(half, rows, q), want)
            other: list = []
            t = threading.Thread(target=lambda: other.append(exact_sq_l2(half, rows, q)))
            t.start()
            t.join()
            assert np.array_equal(other[0], want)
            m.setattr(indexes, "_cv2", lambda: None)  # FAISS's decoder
            assert np.array_equal(exact_sq_l2(half, rows, q), want)
    assert exact_sq_l2(half, rows[:0], q).shape == (0,)
    with pytest.raises(IndexError):  # a few rows: fresh arrays (numpy's own bounds check)
        exact_sq_l2(half, np.array([0, len(half)]), q)
    wide = np.zeros((300, 512), np.float16)  # the thread's buffers: rows checked (take, clip)
    many = np.arange(len(wide))
    for bad in (many + 1, many - 1):
        with pytest.raises(IndexError, match="re-rank rows"):
            exact_sq_l2(wide, bad, np.zeros((1, 512), np.float32))


def test_unique_ints_is_numpy_unique():
    """The sort-based unique of a pass's keys equals ``np.unique`` (empty, one, repeats)."""
    from vlm_vpr_ros.maps.search import unique_ints

    rng = np.random.default_rng(2)
    for n in (0, 1, 2, 7, 800):
        for hi in (1, 3, 2 ** 50):
            a = rng.integers(0, hi, n, dtype=np.int64)
            assert np.array_equal(unique_ints(a), np.unique(a))
            assert unique_ints(a).dtype == np.int64


def test_sorted_member_is_numpy_isin():
    """The binary-search membership of the global merge and the re-rank equals ``np.isin``
    against a sorted array (empty either side, repeats, keys beyond both ends)."""
    from vlm_vpr_ros.maps.search import sorted_member

    rng = np.random.default_rng(4)
    for na in (0, 1, 5, 50, 800):
        for nb in (0, 1, 3, 50, 800):
            for hi in (4, 1000, 2 ** 50):
                a = rng.integers(0, hi, na, dtype=np.int64)
                b = np.sort(rng.integers(0, hi, nb, dtype=np.int64))
                assert np.array_equal(sorted_member(a, b), np.isin(a, b)), (na, nb, hi)


def test_one_faiss_thread_is_per_thread_and_restored(maps):
    """A query's pass runs FAISS single-threaded on its own thread only, and restores it."""
    import threading

    import faiss

    from vlm_vpr_ros.maps.search import one_faiss_thread

    m, desc, _ = maps["flat"]
    outer = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(2)  # a team to narrow, even where the suite runs on one thread
    before = faiss.omp_get_max_threads()
    m.search_submaps(list(range(len(m.submaps))), desc[:1], 5)
    assert faiss.omp_get_max_threads() == before
    inside, release, seen = threading.Event(), threading.Event(), {}

    def worker():
        with one_faiss_thread():
            seen["worker"] = faiss.omp_get_max_threads()
            inside.set()
            release.wait(30)

    t = threading.Thread(target=worker)
    t.start()
    assert inside.wait(30)
    seen["main"] = faiss.omp_get_max_threads()
    release.set()
    t.join(30)
    faiss.omp_set_num_threads(outer)
    assert seen == {"worker": 1, "main": before} and before == 2


def test_pooled_submap_changed_on_disk_fails_the_query(maps, tmp_path):
    """The pool is a copy in RAM, yet a small submap whose index file is truncated after the
    map was opened fails the queries it answers, as a submap searched alone does."""
    from vlm_vpr_ros.errors import MapError

    m, desc, _ = maps["flat"]
    m.save(tmp_path / "map")
    loaded = ReferenceMap.load(tmp_path / "map")
    loc = Localizer(loaded)
    best = loc.localize(desc[0], None).candidates[0]
    si = loaded.submap_index(best.submap)
    assert loaded.small_submaps().pooled[si]
    path = tmp_path / "map" / loaded.submaps[si].files["index"]
    with open(path, "r+b") as fh:
        fh.truncate(path.stat().st_size // 2)
    with pytest.raises(MapError, match="after the map was opened"):
        loc.localize(desc[0], None)


def test_a_few_pooled_submaps_are_searched_alone(maps, monkeypatch):
    """The paper's one small submap (or a few) is searched alone, not through a scan of the
    whole pool, when that reads fewer bytes (issue 31); the same hits either way, and a query
    over every submap still scans the pool once."""
    from vlm_vpr_ros.maps import search

    m, desc, copies = maps["flat"]
    small = m.small_submaps()
    pooled = np.flatnonzero(small.pooled)
    assert len(pooled) > 10
    assert small.pays(pooled[:3])  # this tiny pool (24-D) costs less than 3 calls ...
    monkeypatch.setattr(search, "CALL_BYTES", 96 * 8)  # ... a call worth 8 rows: as at 512-D
    calls = []
    hits = small.hits
    monkeypatch.setattr(small, "hits", lambda *a: calls.append(1) or hits(*a))
    rng = np.random.default_rng(11)
    for t in range(6):
        few = [int(i) for i in rng.choice(pooled, 1 + t % 3, replace=False)]
        q = np.ascontiguousarray(desc[copies[t, 0]][None, :])
        assert small.pays(np.array(few)) is False
        assert m.search_submaps(few, q, 50) == search_submaps_v1(m, few, q, 50)
    assert calls == []
    everything = list(range(len(m.submaps)))
    assert small.pays(pooled)
    assert m.search_submaps(everything, q, 50) == search_submaps_v1(m, everything, q, 50)
    assert calls == [1]
