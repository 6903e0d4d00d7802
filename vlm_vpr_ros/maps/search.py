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

Merging is numpy, not one Python tuple per hit: a country partition has hundreds of small
submaps, and per-hit Python work was a measurable part of a whole-map search.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

#: ranked hits: (squared L2 float32, submap index int64, row int64), best first
Hits = tuple[np.ndarray, np.ndarray, np.ndarray]

_ROW_BITS = 40  # (submap, row) packed in one int64 key: rows < 2**40, submaps < 2**23


def _empty() -> Hits:
    return np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64)


def _key(submap: np.ndarray, row: np.ndarray) -> np.ndarray:
    return (submap.astype(np.int64) << _ROW_BITS) | row.astype(np.int64)


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


class SubmapPass:
    """The searches of one (1, dim) float32 query over ``submaps`` (a map's submap list), for
    top-``k`` rankings of any sets of them; see the module docstring."""

    def __init__(self, submaps: Sequence[Any], q: np.ndarray, k: int,
                 rerank_factor: int) -> None:
        self.subs, self.q, self.k = submaps, q, int(k)
        self.factor = int(rerank_factor)
        self.kk = self.k * max(1, self.factor)
        self._exact: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._stage1: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._keys = np.zeros(0, np.int64)  # re-ranked pq rows (sorted keys) ...
        self._dist = np.zeros(0, np.float32)  # ... and their exact squared L2

    def rank(self, *sets: Sequence[int]) -> list[Hits]:
        """The top-``k`` of each set of submap indices, best first (ties by submap, row)."""
        plans = [self._plan(s) for s in sets]
        picks = [self._pick(pq) for _, pq in plans]
        self._rerank(picks)
        return [self._merge(exact, pick) for (exact, _), pick in zip(plans, picks)]

    def rank_with_global(self, region: Sequence[int]) -> Hits:
        """The region's top-``k`` and, merged in, the global top-``k`` hits the region's ranking
        lacks: ordered by distance, region first on ties (what the two searches and a stable
        merge of their candidates gave)."""
        (rd, rs, rr), (gd, gs, gr) = self.rank(region, range(len(self.subs)))
        extra = ~np.isin(_key(gs, gr), _key(rs, rr))
        d = np.concatenate([rd, gd[extra]])
        order = np.argsort(d, kind="stable")
        return (d[order], np.concatenate([rs, gs[extra]])[order],
                np.concatenate([rr, gr[extra]])[order])

    # -- the searches (each submap once) ----------------------------------------------------------
    def _plan(self, submaps: Sequence[int]) -> tuple[list[int], list[int]]:
        """(exactly searched submaps, pq submaps ranked together) of a set: flat/fp16 submaps
        alone; pq submaps pooled (a lone pq submap too: its pooled ranking is its own)."""
        live = [int(si) for si in submaps if self.subs[si].count > 0]
        pq = [si for si in live if self.subs[si].kind == "pq"]
        if not pq:
            return live, []
        pooled = set(pq)
        return [si for si in live if si not in pooled], pq

    def _exact_hits(self, si: int) -> tuple[np.ndarray, np.ndarray]:
        hit = self._exact.get(si)
        if hit is None:
            sub = self.subs[si]
            dist, rows = sub.search(self.q, min(self.k, sub.count), self.factor)
            hit = self._exact[si] = (np.asarray(dist, np.float32), np.asarray(rows, np.int64))
        return hit

    def _candidates(self, si: int) -> tuple[np.ndarray, np.ndarray]:
        hit = self._stage1.get(si)
        if hit is None:
            dist, rows = self.subs[si].pq_candidates(self.q, self.kk)
            hit = self._stage1[si] = (np.asarray(dist, np.float32), np.asarray(rows, np.int64))
        return hit

    def _pick(self, pq: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """(submap, row) of the best ``k·rerank_factor`` pq candidates of these submaps."""
        if not pq:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        stage = [self._candidates(si) for si in pq]
        approx = np.concatenate([d for d, _ in stage])
        owner = np.repeat(np.array(pq, dtype=np.int64), [len(r) for _, r in stage])
        rows = np.concatenate([r for _, r in stage])
        if len(approx) > self.kk:
            best = np.argpartition(approx, self.kk - 1)[:self.kk]
            owner, rows = owner[best], rows[best]
        return owner, rows

    def _rerank(self, picks: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Exact distances of the picked rows not re-ranked yet, one read per submap (rows
        ascending); the reads of several submaps' cold pages are queued at once first."""
        keys = np.unique(np.concatenate([_key(o, r) for o, r in picks]))
        keys = keys[~np.isin(keys, self._keys)]
        if not len(keys):
            return
        owner, rows = keys >> _ROW_BITS, keys & ((1 << _ROW_BITS) - 1)
        cuts = np.flatnonzero(np.diff(owner)) + 1
        groups = list(zip(owner[np.r_[0, cuts]].tolist(), np.split(rows, cuts)))
        if len(groups) > 1:  # one submap: measured no gain from the advice, only its cost
            for si, r in groups:
                self.subs[si].prefetch(r, ("vectors",))
        dist = np.concatenate([np.asarray(self.subs[si].exact_sq_l2(r, self.q), np.float32)
                               for si, r in groups])
        self._keys = np.concatenate([self._keys, keys])
        self._dist = np.concatenate([self._dist, dist])
        order = np.argsort(self._keys)
        self._keys, self._dist = self._keys[order], self._dist[order]

    def _merge(self, exact: list[int], pick: tuple[np.ndarray, np.ndarray]) -> Hits:
        if not exact and not len(pick[0]):
            return _empty()
        hits = [self._exact_hits(si) for si in exact]
        owner, rows = pick
        pq_dist = self._dist[np.searchsorted(self._keys, _key(owner, rows))]
        dist = np.concatenate([d for d, _ in hits] + [pq_dist])
        sub = np.concatenate([np.repeat(np.array(exact, dtype=np.int64),
                                        [len(r) for _, r in hits]), owner])
        row = np.concatenate([r for _, r in hits] + [rows])
        return top_k(dist, sub, row, self.k)
