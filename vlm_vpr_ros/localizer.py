"""The localizer: prior → submap(s) → top-p retrieval by squared L2 → haversine re-rank.

Uncertainty radius (1-sigma-like, metres; see README "Uncertainty"):
``sigma = max(floor, sqrt(spread² + (0.5·d_prior)²))``. ``spread`` is the median distance from
the chosen reference to its *visual competitors*: up to ``spread_k`` other candidates whose
descriptor distance is at most ``d_chosen / ambiguity_ratio`` (as plausible as the chosen one,
Lowe-ratio style) — do the places that explain the image agree? ``d_prior`` is the distance from
the chosen reference to the prior — does the visual match agree with the VLM? Always finite:
capped at half the Earth's circumference.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from vlm_vpr_ros.errors import ConfigError, DescriptorError
from vlm_vpr_ros.geodesy import MAX_DISTANCE_KM, haversine_km
from vlm_vpr_ros.map_io import ReferenceMap
from vlm_vpr_ros.partition import country_codes, nearest_centroids
from vlm_vpr_ros.priors.base import Prior, PriorResult
from vlm_vpr_ros.types import Candidate, Hypothesis

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LocalizerConfig:
    top_p: int = 50  # references retrieved before re-ranking
    use_submaps: bool = True  # False: search the whole map (ablation "no submap")
    rerank: bool = True  # False: keep the best descriptor match (ablation "no re-rank")
    n_submaps: int = 1  # search the n submaps nearest to the prior
    uncertainty_floor_m: float = 25.0
    spread_k: int = 5
    ambiguity_ratio: float = 0.9
    far_prior_km: float = 2500.0  # flag a match this far from the prior

    def __post_init__(self) -> None:
        if self.top_p < 1 or self.n_submaps < 1 or self.spread_k < 1:
            raise ConfigError("top_p, n_submaps and spread_k must be >= 1")
        if not 0.0 < self.ambiguity_ratio <= 1.0:
            raise ConfigError("ambiguity_ratio must be in (0, 1]")
        if not (self.uncertainty_floor_m > 0 and math.isfinite(self.uncertainty_floor_m)):
            raise ConfigError("uncertainty_floor_m must be a positive finite number")


class Localizer:
    """Answers "where am I?" for a query descriptor and an optional prior."""

    def __init__(self, ref_map: ReferenceMap, config: LocalizerConfig | None = None) -> None:
        self.map = ref_map
        self.config = config or LocalizerConfig()
        self._all = list(range(len(ref_map.submaps)))
        if ref_map.partition_method == "country":
            country_codes([0.0], [0.0])  # load the reverse geocoder now, not on the first query

    # -- submap choice --------------------------------------------------------------------------
    def select_submaps(self, prior: Prior | None) -> tuple[list[int], list[str]]:
        """Indices of the submaps to search and the flags that choice raises."""
        if prior is None:
            return self._all, ["global"]
        if not self.config.use_submaps:
            return self._all, ["no_submap"]
        n = self.config.n_submaps
        flags: list[str] = []
        chosen: list[int] = []
        if self.map.partition_method == "country":
            cc = country_codes([prior.lat], [prior.lon])[0]
            pieces = self.map.group_members(cc)  # >1 when a big country was split (balanced)
            if not pieces:
                flags.append("prior_not_in_map")
            else:
                near = nearest_centroids(prior.lat, prior.lon, self.map.centroids[pieces], 1)
                chosen.append(pieces[int(near[0])])
        for i in nearest_centroids(prior.lat, prior.lon, self.map.centroids, n + len(chosen)):
            if len(chosen) >= n:
                break
            if int(i) not in chosen:
                chosen.append(int(i))
        return chosen, flags

    # -- retrieval ------------------------------------------------------------------------------
    def search(self, desc: np.ndarray, submaps: list[int], k: int) -> list[Candidate]:
        """Top-``k`` references by squared L2 over the given submaps (exact, merged)."""
        q = np.ascontiguousarray(np.asarray(desc, dtype=np.float32).reshape(1, -1))
        if q.shape[1] != self.map.dim:
            raise DescriptorError(f"query descriptor has dim {q.shape[1]}, the map has "
                                  f"{self.map.dim}")
        found: list[tuple[float, int, int]] = []
        for si in submaps:
            kk = min(k, self.map.submaps[si].count)
            if kk == 0:
                continue
            dist, idx = self.map.search_submap(si, q, kk)  # flat/fp16 exact; pq + re-rank
            found += [(float(d), si, int(j)) for d, j in zip(dist, idx) if j >= 0]
        found.sort(key=lambda t: (t[0], t[1], t[2]))
        out = []
        for d, si, j in found[:k]:
            sub = self.map.submaps[si]
            out.append(Candidate(sub.ids[j], float(sub.coords[j, 0]), float(sub.coords[j, 1]),
                                 d, sub.id))
        return out

    # -- the whole query ------------------------------------------------------------------------
    def localize(self, desc: np.ndarray, prior_result: PriorResult | None = None) -> Hypothesis:
        cfg = self.config
        prior = prior_result.prior if prior_result is not None else None
        flags: list[str] = []
        if prior is None:
            flags.append("no_prior")
            if prior_result is not None and prior_result.reason not in ("", "disabled"):
                flags.append("prior_failed")
        t0 = time.perf_counter()
        submaps, sflags = self.select_submaps(prior)
        flags += sflags
        cands = self.search(desc, submaps, cfg.top_p)
        t1 = time.perf_counter()
        if prior is not None:
            d = haversine_km(prior.lat, prior.lon, [c.lat for c in cands],
                             [c.lon for c in cands])
            cands = [Candidate(c.ref_id, c.lat, c.lon, c.l2_sq, c.submap, float(dk))
                     for c, dk in zip(cands, np.atleast_1d(d))]
        ranked = cands
        if prior is not None and cfg.rerank:
            ranked = sorted(cands, key=lambda c: (c.prior_km, c.l2_sq))
        elif prior is not None:
            flags.append("no_rerank")
        t2 = time.perf_counter()
        best = ranked[0]
        if best.prior_km is not None and best.prior_km > cfg.far_prior_km:
            flags.append("prior_far_from_match")
        hyp = Hypothesis(
            lat=best.lat, lon=best.lon, ref_id=best.ref_id,
            submap="*" if sflags in (["global"], ["no_submap"]) else "+".join(
                self.map.submaps[i].id for i in submaps),
            uncertainty_m=self.uncertainty_m(best, cands),
            candidates=ranked, prior=prior, prior_result=prior_result, flags=tuple(flags),
            timings_ms={"retrieval_ms": (t1 - t0) * 1e3, "rerank_ms": (t2 - t1) * 1e3},
        )
        return hyp

    def uncertainty_m(self, best: Candidate, cands: list[Candidate]) -> float:
        """The documented heuristic radius (module docstring) for the chosen candidate."""
        limit = best.l2_sq / (self.config.ambiguity_ratio ** 2)
        rivals = [c for c in cands if c is not best and c.l2_sq <= limit][:self.config.spread_k]
        spread = 0.0
        if rivals:
            spread = float(np.median(haversine_km(best.lat, best.lon, [c.lat for c in rivals],
                                                  [c.lon for c in rivals])))
        d_prior = best.prior_km or 0.0
        sigma_km = math.hypot(spread, 0.5 * d_prior)
        sigma_m = max(self.config.uncertainty_floor_m, sigma_km * 1000.0)
        return float(min(sigma_m, MAX_DISTANCE_KM * 1000.0))
