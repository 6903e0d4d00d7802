"""The localizer: prior → submap(s) → top-p retrieval by squared L2 → fusion.

Two fusion modes (docs/fusion.md):

* ``posterior`` (default): the prior's confidence region (a quantile of the VLM error model)
  picks every submap it intersects, within a budget of references; on maps small enough
  (``global_merge_max_refs``) the global top-p is merged in, so a prior can never hide the best
  visual match — from the same pass over the map (no submap is searched twice, so this costs
  one global search, :mod:`vlm_vpr_ros.maps.search`). Candidates are scored by visual
  likelihood + prior likelihood (:mod:`vlm_vpr_ros.localization.fusion.posterior`) and the
  estimate is the geographic vote's winner.
* ``paper``: the method of Waheed et al. — the one submap nearest to the prior, top-p, re-rank by
  haversine distance to the prior (``use_submaps`` / ``rerank`` / ``n_submaps`` ablations).

In both modes ``uncertainty_m`` is the calibrated radius that holds the true position with 68 %
probability and ``radius95_m`` the 95 % one, from the posterior over the candidates
(:mod:`vlm_vpr_ros.localization.fusion.calibration`). Always finite: capped at half the Earth's
circumference.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from vlm_vpr_ros.errors import ConfigError, DescriptorError
from vlm_vpr_ros.localization.fusion.calibration import load_calibration
from vlm_vpr_ros.localization.fusion.error_model import ErrorModel, load_error_models
from vlm_vpr_ros.localization.fusion.posterior import fuse, prior_weighted_background
from vlm_vpr_ros.geodesy import MAX_DISTANCE_KM, haversine_km, valid_latlon
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.maps.search import unique_ints
from vlm_vpr_ros.maps.mapped import IdView
from vlm_vpr_ros.maps.submap import submap_radius_km
from vlm_vpr_ros.maps.partition import country_codes, nearest_centroids
from vlm_vpr_ros.priors.provider import Prior, PriorResult, prior_sigma_problem
from vlm_vpr_ros.types import Candidate, Hypothesis

log = logging.getLogger(__name__)

FUSION_MODES = ("posterior", "paper")
BACKGROUND_SAMPLE = 256
#: a submap's hits are read at once when the hits number at least this many per submap touched
#: (one read per submap costs about what 7 single-hit reads cost: issue 31, 50 hits of a 1M map
#: over 28 submaps 0.25 ms at once per submap vs 0.06 ms one by one; one submap 0.03 vs 0.06)
READS_PER_SUBMAP = 7


@dataclass(frozen=True)
class LocalizerConfig:
    top_p: int = 50  # references retrieved before fusion / re-ranking
    fusion: str = "posterior"  # "posterior" (default) or "paper"
    use_submaps: bool = True  # False: search the whole map even with a prior
    rerank: bool = True  # False: ignore the prior when ordering candidates (ablation)
    n_submaps: int = 1  # paper mode: search the n submaps nearest to the prior
    prior_quantile: float = 0.95  # posterior mode: confidence region of the prior
    max_region_refs: int = 2_000_000  # posterior mode: budget of references searched
    global_merge_max_refs: int = 250_000  # merge the global top-p on maps up to this size
    vote_radius_m: float = 25.0  # geographic voting radius
    uncertainty_floor_m: float = 25.0  # smallest radius ever reported (the place's size)
    far_prior_km: float = 2500.0  # flag a match this far from the prior
    error_model: str = ""  # error-model JSON ('' = the shipped one)
    error_model_name: str = ""  # model in that file ('' = per prior source, else default)

    def __post_init__(self) -> None:
        if self.top_p < 1 or self.n_submaps < 1 or self.max_region_refs < 1:
            raise ConfigError("top_p, n_submaps and max_region_refs must be >= 1")
        if self.fusion not in FUSION_MODES:
            raise ConfigError(f"unknown fusion {self.fusion!r}; choices: "
                              f"{', '.join(FUSION_MODES)}")
        if not 0.0 < self.prior_quantile < 1.0:
            raise ConfigError("prior_quantile must be in (0, 1)")
        for name in ("uncertainty_floor_m", "vote_radius_m"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ConfigError(f"{name} must be a positive finite number")


@dataclass(frozen=True)
class Retrieved:
    """One query's retrieved references as arrays, best first: what fusion reads
    (:meth:`Localizer.retrieve`); the :class:`Candidate` objects are made once, after fusion
    (issue 31: the 50 candidates of a query were made twice, ~0.3 ms of a 2.3 ms paper query on
    the CPU of that issue)."""

    l2_sq: np.ndarray  # (n,) float64: the squared L2 distances (float32 values)
    lat: np.ndarray  # (n,) float64
    lon: np.ndarray  # (n,) float64
    ref_ids: list[str]
    submaps: list[str]  # submap id of each reference
    rows: np.ndarray  # (n,) int64: row in its submap

    def __len__(self) -> int:
        return len(self.ref_ids)

    def candidates(self) -> list[Candidate]:
        none = [None] * len(self)
        return Candidate.from_columns(self.ref_ids, self.lat.tolist(), self.lon.tolist(),
                                      self.l2_sq.tolist(), self.submaps, none, none,
                                      self.rows.tolist())

    @classmethod
    def from_candidates(cls, cands: Sequence[Candidate]) -> "Retrieved":
        return cls(np.array([c.l2_sq for c in cands], np.float64),
                   np.array([c.lat for c in cands], np.float64),
                   np.array([c.lon for c in cands], np.float64), [c.ref_id for c in cands],
                   [c.submap for c in cands], np.array([c.row for c in cands], np.int64))


@functools.lru_cache(maxsize=256)
def region_radius_km(model: ErrorModel, quantile: float) -> float:
    """The prior's confidence radius: a quantile of its error model, found by bisection (80
    CDF evaluations, 1.4 ms: cached per model, as the region is chosen on every query)."""
    return model.quantile(quantile)


def robust_scale(l2: np.ndarray) -> float:
    """Visual scale of one query for maps without calibration: the robust spread (1.4826 MAD)
    of its candidates' squared distances, so one exact match does not inflate it."""
    if len(l2) < 3:
        return 1.0
    mad = 1.4826 * _median(np.abs(l2 - _median(l2)))
    return mad if mad > 0 and math.isfinite(mad) else float(np.std(l2)) or 1.0


def _median(x: np.ndarray) -> float:
    """``float(np.median(x))`` of a float64 array by one sort, the same float (the middle
    value, or the two middle values' sum halved, as np.median's mean of two; NaN when there is
    one): 1.3 against 10.7 us for 50 values in isolation on an AVX-512 EPYC (issue 31)."""
    s = np.sort(x)
    n = len(s)
    if n and s[-1] != s[-1]:  # NaN sorts last
        return math.nan
    h = n // 2
    return float(s[h]) if n % 2 else float((s[h - 1] + s[h]) / 2.0)


class Localizer:
    """Answers "where am I?" for a query descriptor and an optional prior."""

    def __init__(self, ref_map: ReferenceMap, config: LocalizerConfig | None = None) -> None:
        self.map = ref_map
        self.config = cfg = config or LocalizerConfig()
        self._all = list(range(len(ref_map.submaps)))
        if ref_map.partition_method == "country":
            country_codes([0.0], [0.0])  # load the reverse geocoder now, not on the first query
        self.error_models = load_error_models(cfg.error_model or None)
        if cfg.error_model_name:
            self.error_models.get(cfg.error_model_name)  # unknown name: error at start-up
        self.calibration = load_calibration(ref_map) or {}
        self._submap_geometry()
        # the last prior's submap choice and weighted background (a fixed hint, a cached
        # answer: a prior that repeats over frames), each (key, value); see select_submaps
        self._last_choice: tuple[tuple, tuple[tuple[int, ...], tuple[str, ...]]] | None = None
        self._last_background: tuple[tuple, tuple[np.ndarray, ...]] | None = None

    def _submap_geometry(self) -> None:
        self._radius_km = np.zeros(len(self.map.submaps))
        for i, s in enumerate(self.map.submaps):
            self._radius_km[i] = submap_radius_km(s)  # v2: from the manifest, no file read
        self._counts = np.array([s.count for s in self.map.submaps], dtype=np.float64)
        self._centroids = self.map.centroids
        self._n_refs = int(self._counts.sum())
        # a fixed sample of reference positions: the support of the posterior's miss component
        rng = np.random.default_rng(0)
        per = np.ceil(BACKGROUND_SAMPLE * self._counts / max(1.0, self._counts.sum()))
        pts, wts = [], []
        for s, k in zip(self.map.submaps, per.astype(int)):
            if s.count:
                rows = np.sort(rng.choice(s.count, size=min(k, s.count), replace=False))
                pts.append(np.asarray(s.coords[rows]))  # v2: coords mapped, index not opened
                wts.append(np.full(len(rows), s.count / len(rows)))
        self._background = ((np.concatenate(pts)[:, 0], np.concatenate(pts)[:, 1],
                             np.concatenate(wts)) if pts else None)

    def error_model_for(self, prior: Prior) -> ErrorModel:
        """The prior's own scale when it carries one, else the fitted model of its source."""
        if prior.sigma_km is not None:
            return ErrorModel.single(prior.sigma_km, name=prior.source)
        if self.config.error_model_name:
            return self.error_models.get(self.config.error_model_name)
        return self.error_models.for_source(prior.source)

    # -- submap choice --------------------------------------------------------------------------
    def select_submaps(self, prior: Prior | None) -> tuple[list[int], list[str]]:
        """Indices of the submaps to search and the flags that choice raises. The choice for
        the last prior is kept: a prior that repeats exactly (same position, sigma, source and
        settings) gets it without the distances to every submap (issue 31: 50-85 us of a query
        on maps of 166-230 submaps)."""
        if prior is None:
            return self._all, ["global"]
        if not self.config.use_submaps:
            return self._all, ["no_submap"]
        key = (prior.lat, prior.lon, prior.sigma_km, prior.source, self.config)
        last = self._last_choice
        if last is not None and last[0] == key:
            return list(last[1][0]), list(last[1][1])
        chosen, flags = (self._region_submaps(prior) if self.config.fusion == "posterior"
                         else self._nearest_submaps(prior))
        self._last_choice = (key, (tuple(chosen), tuple(flags)))
        return chosen, flags

    def _nearest_submaps(self, prior: Prior) -> tuple[list[int], list[str]]:
        """The paper's choice: the ``n_submaps`` submaps nearest to the prior (on a country
        partition, the prior's country first)."""
        n = self.config.n_submaps
        flags: list[str] = []
        chosen: list[int] = []
        if self.map.partition_method == "country":
            cc = country_codes([prior.lat], [prior.lon])[0]
            pieces = self.map.group_members(cc)  # >1 when a big country was split (balanced)
            if not pieces:
                flags.append("prior_not_in_map")
            else:
                near = nearest_centroids(prior.lat, prior.lon, self._centroids[pieces], 1)
                chosen.append(pieces[int(near[0])])
        for i in nearest_centroids(prior.lat, prior.lon, self._centroids, n + len(chosen)):
            if len(chosen) >= n:
                break
            if int(i) not in chosen:
                chosen.append(int(i))
        return chosen, flags

    def _region_submaps(self, prior: Prior) -> tuple[list[int], list[str]]:
        """Submaps intersecting the prior's confidence region, nearest first, within budget."""
        radius = region_radius_km(self.error_model_for(prior), self.config.prior_quantile)
        cents = self._centroids
        gap = np.atleast_1d(haversine_km(prior.lat, prior.lon, cents[:, 0], cents[:, 1]))
        gap = np.maximum(gap - self._radius_km, 0.0)
        order = np.argsort(gap, kind="stable")
        order = order[self._counts[order] > 0]
        if not len(order):
            return [], []
        # nearest first: the nearest always; then up to the first submap outside the region
        # (no flag) or over the budget of references (flag), whichever comes first
        g = gap[order]
        outside = np.flatnonzero(g[1:] > radius)
        over = np.flatnonzero(np.cumsum(self._counts[order])[1:] > self.config.max_region_refs)
        stop_out = int(outside[0]) + 1 if len(outside) else len(order)
        stop_over = int(over[0]) + 1 if len(over) else len(order)
        flags = ["region_budget"] if stop_over < stop_out else []
        if g[0] > radius:
            flags.append("prior_not_in_map")
        return order[:min(stop_out, stop_over)].tolist(), flags

    # -- retrieval ------------------------------------------------------------------------------
    def search(self, desc: np.ndarray, submaps: list[int], k: int,
               with_global: bool = False) -> list[Candidate]:
        """Top-``k`` references by squared L2 over the given submaps (exact, merged).
        ``with_global``: plus the map's global top-``k`` references not among them, merged by
        distance, from the same pass (no submap is searched twice; see
        :meth:`ReferenceMap.rank_submaps`)."""
        return self.retrieve(desc, submaps, k, with_global).candidates()

    def retrieve(self, desc: np.ndarray, submaps: list[int], k: int,
                 with_global: bool = False) -> Retrieved:
        """:meth:`search` as arrays (what :meth:`localize` fuses): the hits' positions and ids
        read once per submap when the hits gather in a few submaps (:data:`READS_PER_SUBMAP`),
        else one hit at a time."""
        q = np.ascontiguousarray(np.asarray(desc, dtype=np.float32).reshape(1, -1))
        if q.shape[1] != self.map.dim:
            raise DescriptorError(f"query descriptor has dim {q.shape[1]}, the map has "
                                  f"{self.map.dim}")
        dist, sub, row = self.map.rank_submaps(list(submaps), q, k, with_global)  # pq: re-rank
        n = len(dist)
        lat, lon = np.empty(n), np.empty(n)
        ids: list[str] = [""] * n
        labels: list[str] = [""] * n
        touched = unique_ints(sub).tolist()
        if len(touched) * READS_PER_SUBMAP <= n:  # few submaps (paper: one): a read each
            for si in touched:
                s = self.map.submaps[si]
                at = np.flatnonzero(sub == si)
                rows = row[at]
                xy = np.asarray(s.coords[rows], dtype=np.float64)
                lat[at], lon[at] = xy[:, 0], xy[:, 1]
                names = (s.ids.take(rows) if isinstance(s.ids, IdView)
                         else [s.ids[j] for j in rows])
                for i, name in zip(at.tolist(), names):
                    ids[i], labels[i] = name, s.id
        else:  # hits spread over many submaps: one hit at a time is cheaper
            la, lo = [], []
            for i, (si, j) in enumerate(zip(sub.tolist(), row.tolist())):
                s = self.map.submaps[si]
                coords = s.coords
                la.append(coords.item(j, 0))
                lo.append(coords.item(j, 1))
                ids[i], labels[i] = s.ids[j], s.id
            lat, lon = np.array(la, np.float64), np.array(lo, np.float64)
        return Retrieved(dist.astype(np.float64), lat, lon, ids, labels, row.astype(np.int64))

    # -- the whole query ------------------------------------------------------------------------
    def localize(self, desc: np.ndarray, prior_result: PriorResult | None = None) -> Hypothesis:
        cfg = self.config
        prior = prior_result.prior if prior_result is not None else None
        flags: list[str] = []
        # the last guard of every entry point (priors CSV, options, topic, a provider of the
        # user's): a sigma outside the error model's range is refused here by the one sigma
        # rule, never handed to the model (an error on every query)
        if prior is not None and not (valid_latlon(prior.lat, prior.lon) and (
                prior.sigma_km is None or not prior_sigma_problem(prior.sigma_km))):
            flags += ["prior_failed", "prior_invalid"]
            log.warning("ignoring an invalid prior (%s, %s, sigma %s km) from %s", prior.lat,
                        prior.lon, prior.sigma_km, prior.source)
            prior = None
        if prior is None:
            flags.append("no_prior")
            if (prior_result is not None and prior_result.reason not in ("", "disabled")
                    and "prior_failed" not in flags):
                flags.append("prior_failed")
        t0 = time.perf_counter()
        submaps, sflags = self.select_submaps(prior)
        flags += sflags
        searched_all = len(submaps) == len(self._all)
        # posterior on a small map: the region's top-p + the global top-p, one pass
        with_global = (cfg.fusion == "posterior" and prior is not None and not searched_all
                       and self._n_refs <= cfg.global_merge_max_refs)
        cands = self.retrieve(desc, submaps, cfg.top_p, with_global)
        searched_all = searched_all or with_global
        t1 = time.perf_counter()
        if not len(cands):
            return self._no_match(prior, prior_result, flags, (t1 - t0) * 1e3)
        hyp = self._fuse(cands, prior, prior_result, flags, submaps, searched_all)
        t2 = time.perf_counter()
        hyp.timings_ms = {"retrieval_ms": (t1 - t0) * 1e3, "rerank_ms": (t2 - t1) * 1e3}
        return hyp

    def _fuse(self, cands: Retrieved, prior: Prior | None,
              prior_result: PriorResult | None, flags: list[str], submaps: list[int],
              searched_all: bool) -> Hypothesis:
        cfg = self.config
        cal = self.calibration
        lat, lon, l2 = cands.lat, cands.lon, cands.l2_sq
        model = self.error_model_for(prior) if prior is not None else None
        scale = cal.get("visual_scale") or robust_scale(l2)
        fixed_best = None
        g = order = None
        if prior is not None and cfg.fusion == "paper":
            if cfg.rerank:
                g = np.atleast_1d(haversine_km(prior.lat, prior.lon, lat, lon))
                order = np.lexsort((l2, g))  # by distance to the prior, then descriptor
                fixed_best = int(order[0])
            else:
                flags.append("no_rerank")
                fixed_best = 0
        elif prior is not None and not cfg.rerank:
            flags.append("no_rerank")
        background, weighted = self._background, False
        if background is not None and model is not None and cfg.rerank:
            key = (prior.lat, prior.lon, model)
            last = self._last_background
            if last is None or last[0] != key:
                last = self._last_background = (key, prior_weighted_background(
                    background, (prior.lat, prior.lon), model))
            background, weighted = last[1], True
        post = fuse(l2, lat, lon, scale, float(cal.get("beta", 1.0)),
                    prior=(prior.lat, prior.lon) if prior is not None else None,
                    error_model=model, use_prior_term=cfg.rerank,
                    vote_radius_m=cfg.vote_radius_m, miss_prob=float(cal.get("miss_prob", 0.05)),
                    background=background, background_weighted=weighted,
                    fixed_best=fixed_best if fixed_best is not None else (
                        0 if prior is None and cfg.fusion == "paper" else None),
                    prior_km=g)
        g_km = post.extra["prior_km"]
        out = Candidate.from_columns(
            cands.ref_ids, lat.tolist(), lon.tolist(), l2.tolist(), cands.submaps,
            [None] * len(cands) if g_km is None else g_km.tolist(), post.weights.tolist(),
            cands.rows.tolist())
        best = post.best
        # the others: paper with a prior by (distance to the prior, descriptor distance),
        # paper without one in retrieval order, posterior by weight; numpy's stable sorts
        # give the order Python's stable sort of the candidates by these keys gave
        if order is None and cfg.fusion != "paper":
            order = np.argsort(-post.weights, kind="stable")
        rest = [out[i] for i in (range(len(out)) if order is None else order.tolist())
                if i != best]
        ranked = [out[best], *rest]
        chosen = ranked[0]
        if chosen.prior_km is not None and chosen.prior_km > cfg.far_prior_km:
            flags.append("prior_far_from_match")
        r68, r95 = self.calibrated_radii(post.r68_m, post.r95_m, prior is not None)
        if searched_all:
            label = "*"
        else:
            label = "+".join(self.map.submaps[i].id for i in submaps)
        return Hypothesis(
            lat=chosen.lat, lon=chosen.lon, ref_id=chosen.ref_id, submap=label,
            uncertainty_m=r68, radius95_m=r95, confidence=float(post.votes[best]),
            fusion=cfg.fusion, candidates=ranked, prior=prior, prior_result=prior_result,
            flags=tuple(flags))

    @property
    def calibration_source(self) -> str:
        """Where the radii's calibration comes from: user / map leave-one-out / none."""
        if self.calibration.get("user"):
            return "user (vlm-vpr calibrate)"
        n = (self.calibration.get("loo") or {}).get("queries", 0)
        return f"map leave-one-out ({n} queries)" if n else "none (uncalibrated)"

    def calibration_factors(self, with_prior: bool) -> tuple[float, float]:
        """(k68, k95): a user calibration (``vlm-vpr calibrate``) for the regime when there is
        one, else the larger of the map's leave-one-out factors over both regimes (a simulated
        prior is not the user's prior: the conservative choice, docs/fusion.md)."""
        regime = "prior" if with_prior else "no_prior"
        user = (self.calibration.get("user") or {}).get(regime)
        if user:
            return float(user["k68"]), float(user["k95"])
        loo = list((self.calibration.get("regimes") or {}).values())
        if not loo:
            return 1.0, 1.0
        return max(float(f["k68"]) for f in loo), max(float(f["k95"]) for f in loo)

    def calibrated_radii(self, raw68_m: float, raw95_m: float,
                         with_prior: bool) -> tuple[float, float]:
        k68, k95 = self.calibration_factors(with_prior)
        floor, cap = self.config.uncertainty_floor_m, MAX_DISTANCE_KM * 1000.0
        r68 = min(max(floor, k68 * max(raw68_m, floor)), cap)
        r95 = min(max(r68, k95 * max(raw95_m, floor)), cap)
        return float(r68), float(r95)

    def _no_match(self, prior: Prior | None, prior_result: PriorResult | None,
                  flags: list[str], retrieval_ms: float) -> Hypothesis:
        """Zero candidates (empty map or submaps): a flagged hypothesis, never an exception."""
        cap = MAX_DISTANCE_KM * 1000.0
        lat, lon = (prior.lat, prior.lon) if prior is not None else (math.nan, math.nan)
        return Hypothesis(lat=lat, lon=lon, ref_id="", submap="", uncertainty_m=cap,
                          radius95_m=cap, confidence=0.0, fusion=self.config.fusion,
                          candidates=[], prior=prior, prior_result=prior_result,
                          flags=tuple(flags + ["no_match"]),
                          timings_ms={"retrieval_ms": retrieval_ms, "rerank_ms": 0.0})
