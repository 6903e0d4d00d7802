"""Verified evidence of one query: the winner, its inlier ratio, and the prior's part in it.

Input: the top-K candidates in posterior order, their positions and geometric inlier counts
(-1: not verified), and optionally the prior's log-density at each candidate.

* **Winner**: the candidate with the most inliers among those above the noise level
  (``competitor_floor``: MAGSAC finds 8-13 "inliers" among random matches); with a prior, only
  among those the prior makes less than ``prior_gate`` times less likely than the most likely
  such candidate. Ties go to the earlier (more probable) candidate; with none above the noise
  level the posterior's best stays the answer. **Near ties between places, with a prior**:
  when a candidate farther than ``place_radius_m`` from that winner holds more than
  1 / :data:`AMBIGUOUS_RATIO` of its inliers, geometry cannot tell the two places apart (the
  answer's ``p_correct`` is capped below 2/3 anyway); the place that comes first in posterior
  order (visual similarity and prior) is the answer, represented by its candidate with the most
  inliers. Without a prior the most inliers win, as in hloc. (A place and its look-alike
  elsewhere give about the same inliers: the max alone would pick either of them.)
* **Inlier ratio** (the score): winner inliers / (1 + the most inliers of any candidate farther
  than ``place_radius_m`` from the winner), the competitor count floored at the noise level so
  that a winner with a handful of chance inliers never scores high against candidates without
  matches. A right answer stands out from every other place; a wrong one usually has a
  look-alike with as many inliers (the same landmark seen from 30-350 m away).
* **Prior gate**: with a prior, competitors the prior makes >= ``prior_gate`` times less likely
  than the winner are left out of the ratio (the "gated" score). When only the gated score is
  decisive the answer is ``prior_resolved``: it is as right as the prior (docs/verification.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.geodesy import EARTH_RADIUS_KM, latlon_to_unit

#: below this inlier ratio another place holds at least half the winner's evidence: the
#: answer is a near tie (with a prior, the posterior decides between the tied places), and
#: p_correct is capped at ratio / (1 + ratio) (<= 2/3) whatever the map's wrong answers look
#: like (a sparse map's leave-one-out has few strong look-alikes)
AMBIGUOUS_RATIO = 2.0

@dataclass(frozen=True)
class EvidenceConfig:
    place_radius_m: float = 25.0  # a right answer is within this of the truth
    competitor_floor: int = 12  # geometric noise level (inliers)
    prior_gate: float = 1e4  # competitors this much less likely under the prior are dropped

    def __post_init__(self) -> None:
        if not (self.place_radius_m > 0 and self.competitor_floor >= 0
                and self.prior_gate > 1 and math.isfinite(self.prior_gate)):
            raise ConfigError("evidence: place_radius_m > 0, competitor_floor >= 0 and a "
                              "finite prior_gate > 1 required")


@dataclass
class Evidence:
    winner: int  # index of the answer among the candidates
    winner_inliers: int
    competitor_inliers: int  # most inliers of a competitor the ratio counts (gated)
    competitor_inliers_ungated: int
    score: float  # inlier ratio with prior-gated competitors (= ungated without a prior)
    score_ungated: float
    order: list[int] = field(default_factory=list)  # candidates re-ranked by the evidence
    gated: int = 0  # competitors dropped by the prior gate

    def ratio(self, floor: int, gated: bool = True) -> float:
        c = self.competitor_inliers if gated else self.competitor_inliers_ungated
        return self.winner_inliers / (1.0 + max(c, floor))


def weigh(lat: np.ndarray, lon: np.ndarray, inliers: np.ndarray,
          prior_log_density: np.ndarray | None = None,
          cfg: EvidenceConfig = EvidenceConfig()) -> Evidence:
    """The evidence of one query (module docstring); arrays of equal length > 0, candidates in
    posterior order, ``inliers`` -1 where not verified."""
    inl = np.asarray(inliers, dtype=np.int64)
    n = len(inl)
    floor = int(cfg.competitor_floor)
    log_gate = math.log(cfg.prior_gate)
    logp = (np.asarray(prior_log_density, dtype=np.float64)
            if prior_log_density is not None else None)
    strong = np.flatnonzero(inl > floor)
    if len(strong) and logp is not None:
        strong = strong[logp[strong] >= logp[strong].max() - log_gate]
    winner = int(strong[np.argmax(inl[strong])]) if len(strong) else 0  # first max: earliest
    xyz = latlon_to_unit(np.asarray(lat, np.float64), np.asarray(lon, np.float64))
    cos_r = math.cos(cfg.place_radius_m / 1000.0 / EARTH_RADIUS_KM)
    if len(strong) and logp is not None:
        winner = _first_of_near_tie(winner, strong, inl, xyz, cos_r)
    far = (xyz @ xyz[winner]) < cos_r
    comp = far & (inl >= 0)
    gate = np.zeros(n, bool)
    if logp is not None:
        gate = comp & (logp < logp[winner] - log_gate)
    iw = max(int(inl[winner]), 0)
    cu = int(inl[comp].max()) if comp.any() else 0
    cg = int(inl[comp & ~gate].max()) if (comp & ~gate).any() else 0
    rest = [i for i in range(n) if i != winner]
    order = [winner] + sorted(rest, key=lambda i: (-(inl[i] if inl[i] > floor else 0), i))
    ev = Evidence(winner, iw, cg, cu, 0.0, 0.0, order, int(gate.sum()))
    ev.score, ev.score_ungated = ev.ratio(floor, True), ev.ratio(floor, False)
    return ev


def _first_of_near_tie(winner: int, strong: np.ndarray, inl: np.ndarray, xyz: np.ndarray,
                       cos_r: float) -> int:
    """The winner after a near tie between places (module docstring): the strongest candidate
    of the place that comes first in posterior order among ``winner``'s and those of the other
    places holding more than 1 / AMBIGUOUS_RATIO of its inliers."""
    here = (xyz[strong] @ xyz[winner]) >= cos_r
    rivals = strong[(inl[strong] * AMBIGUOUS_RATIO > inl[winner]) & ~here]
    if not len(rivals) or rivals.min() > strong[here].min():
        return winner
    first = int(rivals.min())
    same = strong[(xyz[strong] @ xyz[first]) >= cos_r]
    return int(same[np.argmax(inl[same])])


def spread_radii(lat: np.ndarray, lon: np.ndarray, winner: int,
                 quantiles: tuple[float, ...] = (0.68, 0.95)) -> tuple[float, ...]:
    """Radii (m) around candidate ``winner`` holding the given shares of all the candidates'
    positions: where the answer may be when geometry supports none of them better than the
    others (the visually similar places, each as likely)."""
    xyz = latlon_to_unit(np.asarray(lat, np.float64), np.asarray(lon, np.float64))
    cos_d = np.clip(xyz @ xyz[winner], -1.0, 1.0)
    dist_m = np.arccos(cos_d) * EARTH_RADIUS_KM * 1000.0
    return tuple(float(np.quantile(dist_m, q, method="inverted_cdf")) for q in quantiles)
