"""The posterior's retrieval as it was before issue 23, kept as the tests' reference: the region
searched, then the whole map searched again for the global top-p, candidates merged by a stable
sort on distance. The product now does it in one pass (vlm_vpr_ros/maps/search.py); tests
compare the two candidate by candidate and answer by answer."""

from __future__ import annotations

import dataclasses

import numpy as np

from vlm_vpr_ros.localization.localizer import Localizer, Retrieved
from vlm_vpr_ros.types import Candidate


def search_submaps_v1(m, submaps, q, k):
    """ReferenceMap.search_submaps before issue 23 (prefetch advice left out: no effect on the
    results): flat/fp16 submaps one by one, pq submaps pooled when more than one submap is
    live, Python tuples sorted by (distance, submap, row)."""
    found = []
    live = [si for si in submaps if m.submaps[si].count > 0]
    pq = [si for si in live if m.submaps[si].kind == "pq"] if len(live) > 1 else []
    for si in live:
        if si not in pq:
            dist, idx = m.submaps[si].search(q, min(k, m.submaps[si].count), m.rerank_factor)
            found += [(float(d), si, int(j)) for d, j in zip(dist, idx) if j >= 0]
    if pq:
        kk = k * max(1, m.rerank_factor)
        stage1 = [m.submaps[si].pq_candidates(q, kk) for si in pq]
        approx = np.concatenate([d for d, _ in stage1])
        owner = np.concatenate([np.full(len(r), si) for si, (_, r) in zip(pq, stage1)])
        rows = np.concatenate([r for _, r in stage1])
        if len(approx) > kk:
            best = np.argpartition(approx, kk - 1)[:kk]
            owner, rows = owner[best], rows[best]
        for si in np.unique(owner).tolist():
            r = np.sort(rows[owner == si])
            dist = m.submaps[si].exact_sq_l2(r, q)
            found += [(float(d), si, int(j)) for d, j in zip(dist, r)]
    found.sort()
    return found[:k]


def two_searches_v1(m, region, q, k):
    """The region's top-k, then the global top-k hits it lacks, stably merged by distance."""
    found = search_submaps_v1(m, region, q, k)
    seen = {(si, j) for _, si, j in found}
    extra = [h for h in search_submaps_v1(m, list(range(len(m.submaps))), q, k)
             if (h[1], h[2]) not in seen]
    return sorted(found + extra, key=lambda h: h[0])


class TwoSearchLocalizer(Localizer):
    """The localizer with the pre-issue-23 retrieval: region search + a second, global one."""

    def _candidates(self, q, submaps, k):
        out = []
        for d, si, j in search_submaps_v1(self.map, list(submaps), q, k):
            sub = self.map.submaps[si]
            out.append(Candidate(sub.ids[j], float(sub.coords[j, 0]), float(sub.coords[j, 1]),
                                 d, sub.id, row=int(j)))
        return out

    def search(self, desc, submaps, k, with_global=False):
        q = np.ascontiguousarray(np.asarray(desc, dtype=np.float32).reshape(1, -1))
        cands = self._candidates(q, submaps, k)
        if with_global:
            seen = {(c.submap, c.ref_id) for c in cands}
            extra = [c for c in self._candidates(q, self._all, k)
                     if (c.submap, c.ref_id) not in seen]
            cands = sorted(cands + extra, key=lambda c: c.l2_sq)
        return cands

    def retrieve(self, desc, submaps, k, with_global=False):
        """What ``localize`` fuses: this class's candidates as arrays."""
        return Retrieved.from_candidates(self.search(desc, submaps, k, with_global))


def answer(h):
    """Everything a hypothesis says except its timings."""
    return {f.name: getattr(h, f.name) for f in dataclasses.fields(h) if f.name != "timings_ms"}


def assert_same_answers(new: Localizer, ref: TwoSearchLocalizer, queries, priors) -> int:
    """Every query: identical candidates (ids, distances, submaps, order) from the one-pass and
    the two-search retrieval, and identical hypotheses; returns how many merged the global
    top-p (so a test can check it exercised the merge)."""
    merged = 0
    for i, (q, pr) in enumerate(zip(queries, priors)):
        prior = pr.prior if pr is not None else None
        submaps, _ = new.select_submaps(prior)
        with_global = (new.config.fusion == "posterior" and prior is not None
                       and len(submaps) != len(new._all)
                       and new.map.n_references <= new.config.global_merge_max_refs)
        merged += with_global
        got = new.search(q, submaps, new.config.top_p, with_global)
        want = ref.search(q, submaps, ref.config.top_p, with_global)
        assert got == want, f"query {i}: candidates differ"
        assert answer(new.localize(q, pr)) == answer(ref.localize(q, pr)), f"query {i}"
    return merged
