"""Posterior over retrieved candidates, geographic voting and the 68 / 95 % radii.

For candidate ``i`` with squared descriptor distance ``d_i`` and great-circle distance ``g_i`` to
the prior::

    log w_i = -beta * (d_i - min_j d_j) / T  +  log p_err(g_i)      (then normalized)

``T`` is the map's visual scale (nearest-neighbour statistics stored at build time, or the
query's own candidate spread for maps without them), ``beta`` its calibrated sharpness, and
``p_err`` the prior's error model as an areal density (see :mod:`.error_model`). Without a prior
the second term is absent.

Geographic voting: the estimate is the candidate with the largest posterior mass within
``vote_radius_m`` of it (places that agree add up), ties broken by the candidate's own weight;
only the 64 most probable candidates vote and can win (the others' mass is negligible).

Radii: the smallest radius around the estimate that holds 68 % (95 %) of a mixture of the
candidates' posterior masses (each a point) and a *miss* component of mass ``m0`` — the chance
that no candidate is the place — spread over the map's references (a fixed sample of their
positions), weighted by the prior's likelihood when there is a prior. The raw radii are then
multiplied by conformal factors (:mod:`.calibration`) and floored at the place radius.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from vlm_vpr_ros.localization.fusion.error_model import ErrorModel
from vlm_vpr_ros.geodesy import EARTH_RADIUS_KM, MAX_DISTANCE_KM, haversine_km, latlon_to_unit


#: geographic voting considers this many most probable candidates
VOTERS = 64


@dataclass
class Posterior:
    weights: np.ndarray  # (n,) normalized posterior weight of each candidate
    votes: np.ndarray  # (n,) posterior mass within the vote radius of each candidate
    best: int  # index of the estimate
    r68_m: float  # raw (uncalibrated) radii around the estimate
    r95_m: float
    miss_mass: float
    extra: dict = field(default_factory=dict)


def _mixture_radii(qs: tuple[float, ...], point_d_km: np.ndarray, point_w: np.ndarray,
                   miss_mass: float, miss_cdf: Callable[[np.ndarray], np.ndarray],
                   steps: tuple[np.ndarray, np.ndarray] | None = None) -> list[float]:
    """For each q: the smallest r (km) with sum(point_w[d <= r]) + miss_mass * miss_cdf(r) >= q.

    ``steps``: (sorted distances, CDF after each) when ``miss_cdf`` is that step function (the
    map's background sample): the search then needs no evaluation of it (:func:`_grid_search`,
    the same result)."""
    order = np.argsort(point_d_km, kind="stable")
    d_sorted = point_d_km[order]
    cum = np.cumsum(point_w[order])
    mass_at = cum + miss_mass * miss_cdf(d_sorted)
    out = []
    for q in qs:
        ok = mass_at >= q
        k = int(np.argmax(ok)) if ok.any() else len(d_sorted)
        lo = float(d_sorted[k - 1]) if k > 0 else 0.0
        hi = float(d_sorted[k]) if k < len(d_sorted) else MAX_DISTANCE_KM
        below = float(cum[k - 1]) if k > 0 else 0.0  # point mass inside (lo, hi) is constant
        if k == len(d_sorted) and below + miss_mass * float(miss_cdf(np.array([hi]))[0]) < q:
            out.append(hi)
        elif steps is None:
            out.append(_grid_search(q, lo, hi, below, miss_mass, miss_cdf))
        else:
            out.append(_grid_search_steps(q, lo, hi, below, miss_mass, *steps))
    return out


def _grid_search(q: float, lo: float, hi: float, below: float, miss_mass: float,
                 miss_cdf: Callable[[np.ndarray], np.ndarray]) -> float:
    """The radius inside (lo, hi]: a vectorized bisection, each round evaluating 64 points of
    (lo, hi] at once; 4 rounds shrink the interval 64**4 = 1.7e7 times (50 scalar halvings cost
    10x more per query)."""
    for _ in range(4):
        grid = lo + (hi - lo) * np.arange(1, 65) / 64.0
        ok = below + miss_mass * np.asarray(miss_cdf(grid), dtype=np.float64) >= q
        if not ok.any():
            return hi
        j = int(np.argmax(ok))
        lo, hi = (float(grid[j - 1]) if j else lo), float(grid[j])
    return hi


def _grid_search_steps(q: float, lo: float, hi: float, below: float, miss_mass: float,
                       bd: np.ndarray, bcum: np.ndarray) -> float:
    """:func:`_grid_search` for a step-function miss CDF (``bcum[i]`` from ``bd[i]`` on, 0
    before ``bd[0]``), with the same result: the mass is then at least q exactly from the first
    step whose level reaches q, so each round's first grid point at or beyond that step is found
    by arithmetic on the grid's own floats (``lo + span * (j + 1) / 64.0``, the expression
    numpy evaluates per element), without evaluating the CDF at 64 points (issue 31: two radii
    per query, ~0.1 ms of a 2 ms query on the CPU of that issue)."""
    if below + miss_mass * 0.0 >= q:
        t = -math.inf  # every point of (lo, hi] has the mass
    else:
        hit = np.flatnonzero(below + miss_mass * bcum >= q)
        if not len(hit):
            return hi
        t = float(bd[hit[0]])
    for _ in range(4):
        span = hi - lo
        if not lo + span * 64 / 64.0 >= t:
            return hi
        j = 0
        if t > -math.inf and span > 0:
            x = (t - lo) / span * 64.0  # a first guess (may overflow: then the last point)
            j = 63 if not x < 64.0 else max(0, int(x) - 1)
            while j > 0 and lo + span * j / 64.0 >= t:
                j -= 1
            while not lo + span * (j + 1) / 64.0 >= t:
                j += 1
        lo, hi = (lo + span * j / 64.0 if j else lo), lo + span * (j + 1) / 64.0
    return hi


def prior_weighted_background(background: tuple[np.ndarray, np.ndarray, np.ndarray],
                              prior: tuple[float, float], error_model: ErrorModel
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The miss component's support weighted by the prior's likelihood (what :func:`fuse`
    does with ``background`` when there is a prior term): a function of the prior alone, so a
    caller whose prior repeats (a fixed hint, a cached answer) computes it once and passes it
    with ``background_weighted=True``."""
    blat, blon, bw = (np.asarray(v, dtype=np.float64) for v in background)
    lg = error_model.log_density(haversine_km(prior[0], prior[1], blat, blon))
    return blat, blon, bw * np.exp(lg - np.max(lg))


def fuse(l2_sq: np.ndarray, lat: np.ndarray, lon: np.ndarray, visual_scale: float,
         beta: float = 1.0, prior: tuple[float, float] | None = None,
         error_model: ErrorModel | None = None, use_prior_term: bool = True,
         vote_radius_m: float = 25.0, miss_prob: float = 0.05,
         background: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
         fixed_best: int | None = None, prior_km: np.ndarray | None = None,
         background_weighted: bool = False) -> Posterior:
    """Posterior, vote and raw radii for one query's candidates (arrays of equal length > 0).

    ``miss_prob``: probability that no candidate is the place (calibrated at build time, see
    :mod:`.calibration`). ``background``: (lat, lon, weight) of the map's mass (submap centroids
    and counts), the miss component's spread without a prior. ``fixed_best``: use this candidate
    as the estimate (the paper mode) instead of the vote. ``prior_km``: the candidates'
    great-circle distances to the prior when the caller has them already.
    ``background_weighted``: ``background`` is :func:`prior_weighted_background` of this prior
    and model already."""
    d = np.asarray(l2_sq, dtype=np.float64)
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    scale = visual_scale if visual_scale > 0 and math.isfinite(visual_scale) else 1.0
    logw = -beta * (d - d.min()) / scale
    has_prior = prior is not None and error_model is not None
    g_km = None
    if has_prior:
        g_km = (np.atleast_1d(haversine_km(prior[0], prior[1], lat, lon)) if prior_km is None
                else np.asarray(prior_km, dtype=np.float64))
        if use_prior_term:
            logw = logw + error_model.log_density(g_km)
    logw -= logw.max()
    w = np.exp(logw)
    w /= w.sum()
    # votes: posterior mass within the vote radius of each candidate (unit-vector dot products)
    # votes among the VOTERS most probable candidates (the rest carry negligible mass)
    top = np.argsort(-w, kind="stable")[:VOTERS]
    xyz = latlon_to_unit(lat[top], lon[top])
    dots = (xyz[:, 0, None] * xyz[None, :, 0] + xyz[:, 1, None] * xyz[None, :, 1]
            + xyz[:, 2, None] * xyz[None, :, 2])
    near = dots >= math.cos(vote_radius_m / 1000.0 / EARTH_RADIUS_KM)
    votes = np.zeros_like(w)
    votes[top] = np.where(near, w[top][None, :], 0.0).sum(axis=1)
    if fixed_best is not None:
        best = int(fixed_best)
    else:  # most votes, then own weight (top is sorted by weight: first maximum wins)
        best = int(top[int(np.argmax(np.round(votes[top], 12)))])
    dist_best = np.atleast_1d(haversine_km(lat[best], lon[best], lat, lon))
    miss = float(min(max(miss_prob, 0.0), 1.0))
    steps = None
    if background is not None and len(background[0]):
        if has_prior and use_prior_term and not background_weighted:
            background = prior_weighted_background(background, prior, error_model)
        blat, blon, bw = (np.asarray(v, dtype=np.float64) for v in background)
        bd = np.atleast_1d(haversine_km(lat[best], lon[best], blat, blon))
        order = np.argsort(bd, kind="stable")
        bd = bd[order]
        bcum = np.cumsum(bw[order])
        bcum = bcum / bcum[-1] if bcum[-1] > 0 else np.ones_like(bcum)
        steps = (bd, bcum)

        def miss_cdf(r: np.ndarray) -> np.ndarray:  # truth: a mapped place not retrieved
            k = np.searchsorted(bd, r, side="right")
            return np.where(k > 0, bcum[np.maximum(k - 1, 0)], 0.0)
    elif has_prior:
        g_best = float(g_km[best])

        def miss_cdf(r: np.ndarray) -> np.ndarray:  # truth ~ error model around the prior
            return error_model.cdf(np.maximum(0.0, r - g_best))
    else:
        def miss_cdf(r: np.ndarray) -> np.ndarray:
            return np.zeros_like(np.asarray(r, dtype=np.float64))
    pw = w * (1.0 - miss)
    r68, r95 = (r * 1000.0 for r in _mixture_radii((0.68, 0.95), dist_best, pw, miss, miss_cdf,
                                                    steps))
    return Posterior(w, votes, best, r68, max(r68, r95), miss, {"prior_km": g_km})
