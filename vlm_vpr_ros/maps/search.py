"""One query's search over several submaps of a map: every submap is searched at most once.

The posterior fusion needs two rankings per query: the top-k over the prior's region and, on maps
up to ``global_merge_max_refs`` references, the global top-k over the whole map. Two separate
searches scanned the region's references twice (about two global searches per query with a
VLM's wide prior). :class:`SubmapPass` remembers what it has searched for one query:

* flat / fp16 submaps: FAISS's exact top-``min(k, count)`` of the submap (one scan each);
* pq submaps: stage 1, the ``k·rerank_factor`` best rows by PQ-approximate distance (codes in
  RAM, one fast scan each), and the exact fp16 distance of every row a ranking picked (each row
  re-ranked once, however many rankings picked it).

Any set of submaps is then ranked from these results exactly as a search of that set alone
ranks it: flat/fp16 hits merged by (squared L2, submap, row); the pq candidates of the set's
submaps pooled, the best ``k·rerank_factor`` of them by approximate distance (in the set's
order, as one pq index over their union would pick them) re-ranked exactly. The region's and
the global ranking therefore come from one pass over the map and equal two separate searches
(tests/test_fusion_search.py checks that against the two-search implementation).

Merging is numpy, not one Python tuple per hit. A country partition has hundreds of small
submaps (221 of the 230 of the 100k MP-16 map hold <= 4,096 references, 32 % of them), and a
FAISS call per small submap costs more than its scan: :class:`SmallSubmaps` keeps a copy of
the small flat/fp16 submaps (<= ``POOL_MAX_REFS`` references each, at most ``POOL_MAX_BYTES``:
63 MiB on that map at 512-D, 32 MiB at 256-D; flat rows in huge pages, which a scan reads ~1.4x
faster than an index's own copy, issue 31), scanned with one call per kind that
returns the rows within the k-th distance the pass has already found elsewhere (all rows when
it has none) — the same distances as each submap's own search (same FAISS kernel; checked in
tests/test_fusion_search.py). Taking those rows instead of each small submap's
top-``min(k, count)`` changes no ranking: FAISS keeps the lowest rows on ties, so a row beyond
its submap's top-k has k rows of that submap ahead of it. A query that needs only a few pooled
submaps (the paper's one submap, a tight region without the global merge) searches them alone
when that scans fewer bytes than the whole pool (:data:`CALL_BYTES` per call counted).
Measured on the maps of
``benchmarks/bench_core.py`` (512-D, one process, queries interleaved, load ~3): posterior with
a VLM-like prior / one global search 1.12x with the pool of submaps up to 1,024 references,
1.18x with a pool up to 256 (issue 23, AVX2 EPYC); on the AVX-512 EPYC of issue 31, with the
flat pool in huge pages, 1.09x up to 1,024 and 1.07x up to 4,096 (the 10 FAISS calls then scan
the 100,000 rows as fast as the one global call; each call has ~25 us of its own).

A pass runs FAISS on one OpenMP thread (this thread only; restored afterwards): FAISS splits a
single query's scan of a large index over an OpenMP team, and a team's wake-up costs a
scheduler round when the cores are busy — on this 2-core machine at load 5, a 100k-reference
flat search took 72 ms with the default 2 threads and 20 ms with one, and the 230 country
submaps 25 ms against 6 ms (``benchmarks/bench_core.py`` prints both settings for the flat
search). Batch work (building, recall measurement) keeps FAISS's threads.
"""

from __future__ import annotations

import contextlib
import math
from typing import Any, Iterator, Sequence

import numpy as np

from vlm_vpr_ros.maps.indexes import make_index, range_search_rows, search_exact_many
from vlm_vpr_ros.maps.mapped import huge_page_array

#: ranked hits: (squared L2 float32, submap index int64, row int64), best first
Hits = tuple[np.ndarray, np.ndarray, np.ndarray]

_ROW_BITS = 40  # (submap, row) packed in one int64 key: rows < 2**40, submaps < 2**23
#: submaps of at most this many references are scanned together (module docstring)
POOL_MAX_REFS = 4096
POOL_MAX_BYTES = 64 * 2 ** 20  # the pooled copy's size limit (smallest submaps first)
POOL_MAX_FP16_REFS = 8192  # fp16 is searched for all its rows: a heap that grows with them
#: a FAISS call's fixed cost in bytes scanned (~25 us at ~10 GB/s): a query that needs a few
#: pooled submaps searches them alone when that scans less than the whole pool (paper mode)
CALL_BYTES = 256 * 2 ** 10


def _empty() -> Hits:
    return np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64)


def _key(submap: np.ndarray, row: np.ndarray) -> np.ndarray:
    return (submap.astype(np.int64) << _ROW_BITS) | row.astype(np.int64)


def unique_ints(a: np.ndarray) -> np.ndarray:
    """``np.unique`` of an integer array (sorted, each value once) by a sort: numpy 2's
    ``unique`` hashes first (64 against 10 us for 800 keys on the CPU of issue 31)."""
    a = np.sort(a)
    if len(a) < 2:
        return a
    first = np.empty(len(a), dtype=bool)
    first[0] = True
    np.not_equal(a[1:], a[:-1], out=first[1:])
    return a[first]


def sorted_member(a: np.ndarray, sorted_b: np.ndarray) -> np.ndarray:
    """``np.isin(a, sorted_b)`` for a sorted ``sorted_b`` by a binary search (numpy 2's
    ``isin`` hashes or sorts both: 52 against 4 us for 50 keys on an AVX-512 EPYC)."""
    if not len(sorted_b):
        return np.zeros(len(a), dtype=bool)
    at = np.searchsorted(sorted_b, a)
    np.minimum(at, len(sorted_b) - 1, out=at)
    return sorted_b[at] == a


@contextlib.contextmanager
def one_faiss_thread() -> Iterator[None]:
    """FAISS on one OpenMP thread in this block, on this thread (OpenMP's thread count is a
    per-thread setting: other threads are not affected)."""
    import faiss

    before = faiss.omp_get_max_threads()
    if before == 1:
        yield
        return
    faiss.omp_set_num_threads(1)
    try:
        yield
    finally:
        faiss.omp_set_num_threads(before)


def _members(idx: Any, n: int) -> np.ndarray:
    """A boolean mask over ``n`` submaps, True at the indices ``idx``."""
    mask = np.zeros(n, dtype=bool)
    mask[np.asarray(idx, dtype=np.int64)] = True
    return mask


def _kth(dist: np.ndarray, k: int) -> float:
    """The k-th smallest distance; infinity when there are fewer (or it is NaN)."""
    if len(dist) < k:
        return math.inf
    kth = float(np.partition(dist, k - 1)[k - 1])
    return kth if kth == kth else math.inf


def top_k(dist: np.ndarray, submap: np.ndarray, row: np.ndarray, k: int) -> Hits:
    """The ``k`` best hits by (distance, submap, row); a NaN distance ranks last."""
    if k <= 0:
        return _empty()
    if len(dist) > k:
        kth = np.partition(dist, k - 1)[k - 1]
        keep = np.flatnonzero(~(dist > kth))  # ~(>): NaN k-th keeps everything
        dist, submap, row = dist[keep], submap[keep], row[keep]
    order = np.lexsort((row, submap, dist))[:k]
    return dist[order], submap[order], row[order]


def _dim_of(sub: Any) -> int:
    """A submap's descriptor size, without opening a lazily opened submap."""
    dim = getattr(sub, "dim", None)
    return int(dim) if dim is not None else int(sub.index.d)


class SmallSubmaps:
    """The small flat/fp16 submaps of a submap list, copied together: flat rows into one
    float32 array in huge-page memory (:func:`~vlm_vpr_ros.maps.mapped.huge_page_array`, scanned
    by FAISS's flat kernel), fp16 into one FAISS index (``pool=False``: none; the facts a pass
    plans with only)."""

    def __init__(self, submaps: Sequence[Any], pool: bool = True) -> None:
        self.source = tuple(map(id, submaps))
        #: facts of the submap list a pass plans with (numpy: no Python loop per submap)
        self.live = np.array([s.count > 0 for s in submaps], dtype=bool)
        self.is_pq = np.array([s.kind == "pq" for s in submaps], dtype=bool)
        self.pooled = np.zeros(len(submaps), dtype=bool)
        self.parts: list[tuple[str, Any, np.ndarray, np.ndarray]] = []
        self.pool_bytes = 0  # what one scan of the pool reads
        if pool:
            self._build(submaps)
            self.row_bytes = np.array([_dim_of(s) * (4 if s.kind == "flat" else 2)
                                       if p else 0 for s, p in zip(submaps, self.pooled)])
            self.counts = np.array([s.count for s in submaps], dtype=np.int64)
            self.pool_bytes = sum(int(self.row_bytes[owner].sum())
                                  for _, _, owner, _ in self.parts)

    def pays(self, members: np.ndarray) -> bool:
        """Whether one scan of the pool costs less than searching these pooled submaps alone
        (same hits either way: each submap's own distances)."""
        alone = int((self.counts[members] * self.row_bytes[members]).sum())
        return self.pool_bytes + CALL_BYTES <= alone + CALL_BYTES * len(members)

    def _build(self, submaps: Sequence[Any]) -> None:
        small = sorted((s.count, i) for i, s in enumerate(submaps)
                       if s.kind in ("flat", "fp16") and 0 < s.count <= POOL_MAX_REFS)
        budget, fp16_refs = POOL_MAX_BYTES, 0
        members: dict[str, list[tuple[int, np.ndarray]]] = {"flat": [], "fp16": []}
        for n, i in small:
            kind = submaps[i].kind
            fp16_refs += n if kind == "fp16" else 0
            budget -= n * _dim_of(submaps[i]) * (4 if kind == "flat" else 2)
            if budget < 0:
                break
            if kind == "flat" or fp16_refs <= POOL_MAX_FP16_REFS:
                members[kind].append((i, submaps[i].vectors()))  # float32 (fp16: exact)
        for kind, got in members.items():
            if len(got) < 2:
                continue  # one submap: nothing to save
            got.sort(key=lambda m: m[0])
            if kind == "flat":  # the rows themselves, in huge pages: scanned ~1.4x faster
                store = huge_page_array((sum(len(v) for _, v in got), got[0][1].shape[1]),
                                        np.float32)
                np.concatenate([v for _, v in got], out=store)
            else:
                store = make_index(kind, np.concatenate([v for _, v in got]))
            owner = np.repeat([i for i, _ in got], [len(v) for _, v in got]).astype(np.int64)
            row = np.concatenate([np.arange(len(v), dtype=np.int64) for _, v in got])
            self.parts.append((kind, store, owner, row))
            self.pooled[[i for i, _ in got]] = True

    @property
    def n_refs(self) -> int:
        return sum(len(owner) for _, _, owner, _ in self.parts)

    def hits(self, q: np.ndarray, bound: float = math.inf) -> Hits:
        """(squared L2, submap, row) of every pooled reference at most ``bound`` away; flat: a
        range search (no top-k heap; FAISS keeps distances below its radius: the next float32
        above ``bound``), fp16: a search for all rows (its range search uses another kernel,
        whose distances differ in the last bit for some dims)."""
        dist, sub, row = [], [], []
        radius = float(np.nextafter(np.float32(bound), np.float32(np.inf)))
        for kind, index, owner, rows in self.parts:
            if kind == "flat":  # the pooled rows (an array: _build)
                d, idx = range_search_rows(index, q, radius)
            else:
                d, idx = index.search(q, index.ntotal)
                keep = (idx[0] >= 0) & ~(d[0] > bound)
                d, idx = d[0][keep], idx[0][keep]
            dist.append(np.asarray(d, np.float32))
            sub.append(owner[idx])
            row.append(rows[idx])
        if not dist:
            return _empty()
        return np.concatenate(dist), np.concatenate(sub), np.concatenate(row)


class SubmapPass:
    """The searches of one (1, dim) float32 query over ``submaps`` (a map's submap list), for
    top-``k`` rankings of any sets of them; see the module docstring."""

    def __init__(self, submaps: Sequence[Any], q: np.ndarray, k: int,
                 rerank_factor: int, small: SmallSubmaps | None = None) -> None:
        self.subs, self.q, self.k = submaps, q, int(k)
        self.facts = small if small is not None else SmallSubmaps(submaps, pool=False)
        self.small = self.facts if self.facts.parts else None
        self.factor = int(rerank_factor)
        self.kk = self.k * max(1, self.factor)
        # the hits of the flat/fp16 submaps searched alone, all in three arrays (one mask per
        # ranking picks a set's: few numpy calls, each of which runs cold after the scans)
        self._searched = np.zeros(len(submaps), dtype=bool)
        self._exact: Hits = _empty()
        self._stage1: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._keys = np.zeros(0, np.int64)  # re-ranked pq rows (sorted keys) ...
        self._dist = np.zeros(0, np.float32)  # ... and their exact squared L2

    def rank(self, *sets: Sequence[int]) -> list[Hits]:
        """The top-``k`` of each set of submap indices, best first (ties by submap, row)."""
        plans = [self._plan(s) for s in sets]
        members = unique_ints(np.concatenate([p for _, _, p in plans]))
        if len(members) and not self.small.pays(members):  # a few small submaps: alone
            plans = [(np.concatenate([exact, pooled]), pq, pooled[:0])
                     for exact, pq, pooled in plans]
        with one_faiss_thread():
            self._search_exact(np.concatenate([exact for exact, _, _ in plans]))
            picks = [self._pick(pq) for _, pq, _ in plans]
            self._rerank(picks)
            parts = [self._gather(exact, pick) for (exact, _, _), pick in zip(plans, picks)]
            # the small submaps' pool: only rows that can still enter a ranking, i.e. not
            # beyond the k-th distance a set has already (with ties: the bound is included)
            bound = max((_kth(d, self.k) for (d, _, _), (_, _, pooled) in zip(parts, plans)
                         if len(pooled)), default=None)
            small = _empty() if bound is None else self.small.hits(self.q, bound)
            return [self._with_small(hits, pooled, small)
                    for hits, (_, _, pooled) in zip(parts, plans)]

    def rank_with_global(self, region: Sequence[int]) -> Hits:
        """The region's top-``k`` and, merged in, the global top-``k`` hits the region's ranking
        lacks: ordered by distance, region first on ties (what the two searches and a stable
        merge of their candidates gave)."""
        (rd, rs, rr), (gd, gs, gr) = self.rank(region, np.arange(len(self.subs)))
        if self.facts.is_pq.any():  # the two pq picks can differ on ties: by (submap, row)
            extra = ~sorted_member(_key(gs, gr), np.sort(_key(rs, rr)))
        else:  # a global hit in a region submap ranks as high in the region: already there
            extra = ~_members(region, len(self.subs))[gs]
        d = np.concatenate([rd, gd[extra]])
        order = np.argsort(d, kind="stable")
        return (d[order], np.concatenate([rs, gs[extra]])[order],
                np.concatenate([rr, gr[extra]])[order])

    # -- the searches (each submap once) ----------------------------------------------------------
    def _plan(self, submaps: Sequence[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(flat/fp16 submaps searched alone, pq submaps ranked together, small submaps in the
        pool) of a set's live submaps, each in the set's order (a lone pq submap is ranked as a
        pool of one: the same ranking)."""
        idx = np.asarray(submaps, dtype=np.int64).reshape(-1)
        idx = idx[self.facts.live[idx]]
        pq = self.facts.is_pq[idx]
        rest = idx[~pq]
        pooled = self.facts.pooled[rest]
        return rest[~pooled], idx[pq], rest[pooled]

    def _search_exact(self, sis: np.ndarray) -> None:
        """The top-``min(k, count)`` of the pass's flat/fp16 submaps not searched yet (FAISS's
        exact search), back to back (:func:`~vlm_vpr_ros.maps.indexes.search_exact_many`)."""
        todo = unique_ints(sis)
        todo = todo[~self._searched[todo]]
        if not len(todo):
            return
        subs = [self.subs[si] for si in todo.tolist()]
        d, at, r = search_exact_many([(s.searchable(), min(self.k, s.count)) for s in subs],
                                     self.q)
        self._searched[todo] = True
        if not len(self._exact[0]):  # the pass's first search (most passes: the only one)
            self._exact = (d, todo[at], r)
            return
        dist, sub, row = self._exact
        self._exact = (np.concatenate([dist, d]), np.concatenate([sub, todo[at]]),
                       np.concatenate([row, r]))

    def _candidates(self, si: int) -> tuple[np.ndarray, np.ndarray]:
        hit = self._stage1.get(si)
        if hit is None:
            dist, rows = self.subs[si].pq_candidates(self.q, self.kk)
            hit = self._stage1[si] = (np.asarray(dist, np.float32), np.asarray(rows, np.int64))
        return hit

    def _pick(self, pq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(submap, row) of the best ``k·rerank_factor`` pq candidates of these submaps."""
        if not len(pq):
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        stage = [self._candidates(si) for si in pq.tolist()]
        approx = np.concatenate([d for d, _ in stage])
        owner = np.repeat(pq, [len(r) for _, r in stage])
        rows = np.concatenate([r for _, r in stage])
        if len(approx) > self.kk:
            best = np.argpartition(approx, self.kk - 1)[:self.kk]
            owner, rows = owner[best], rows[best]
        return owner, rows

    def _rerank(self, picks: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Exact distances of the picked rows not re-ranked yet, one read per submap (rows
        ascending); the reads of several submaps' cold pages are queued at once first."""
        if not any(len(owner) for owner, _ in picks):
            return  # no pq submap in the sets
        keys = unique_ints(np.concatenate([_key(o, r) for o, r in picks]))
        if len(self._keys):
            keys = keys[~sorted_member(keys, self._keys)]
        if not len(keys):
            return
        owner, rows = keys >> _ROW_BITS, keys & ((1 << _ROW_BITS) - 1)
        cuts = np.flatnonzero(np.diff(owner)) + 1
        groups = list(zip([int(owner[0])] + owner[cuts].tolist(), np.split(rows, cuts)))
        if len(groups) > 1:  # one submap: measured no gain from the advice, only its cost
            for si, r in groups:
                self.subs[si].prefetch(r, ("vectors",))
        dist = np.concatenate([np.asarray(self.subs[si].exact_sq_l2(r, self.q), np.float32)
                               for si, r in groups])
        if not len(self._keys):  # the pass's first re-rank: already in key order
            self._keys, self._dist = keys, dist
            return
        self._keys = np.concatenate([self._keys, keys])
        self._dist = np.concatenate([self._dist, dist])
        order = np.argsort(self._keys)
        self._keys, self._dist = self._keys[order], self._dist[order]

    def _gather(self, exact: np.ndarray, pick: tuple[np.ndarray, np.ndarray]) -> Hits:
        """The hits of a set's submaps searched alone and of its pq pool."""
        dist, sub, row = self._exact
        keep = _members(exact, len(self.subs))[sub]
        owner, rows = pick
        if not len(owner):
            return dist[keep], sub[keep], row[keep]
        pq_dist = self._dist[np.searchsorted(self._keys, _key(owner, rows))]
        return (np.concatenate([dist[keep], pq_dist]), np.concatenate([sub[keep], owner]),
                np.concatenate([row[keep], rows]))

    def _with_small(self, hits: Hits, pooled: np.ndarray, small: Hits) -> Hits:
        """A set's top-``k``: its own hits and its pooled submaps' rows."""
        dist, sub, row = hits
        if len(pooled) and len(small[0]):
            keep = _members(pooled, len(self.subs))[small[1]]
            dist = np.concatenate([dist, small[0][keep]])
            sub = np.concatenate([sub, small[1][keep]])
            row = np.concatenate([row, small[2][keep]])
        return top_k(dist, sub, row, self.k)
