"""A trusted prior with its own sigma (an operator's hint, the robot's own estimate): how much
it may add to a verified answer, and the guard against one that lies about its sigma (pure).

Applies to answers whose prior carries ``sigma_km`` when the status policy trusts such priors
(``trust_operator_prior``; :meth:`StatusPolicy.trusts`). Called by the verifier (``weigh_prior``,
given by the pipeline) once the candidates are ranked, before the radii and the protection
level are derived from ``p_correct``, so every output sees the same ``p_correct``, radii and
protection level.

**Weight.** Geometry alone gives ``p_correct_without_prior`` (pu) for the winner against its
strongest competitor farther than the place radius (25 m). A prior with its own sigma says how
much likelier the winner's place is than that competitor's: the likelihood ratio LR of the two
distances under the prior's error model (a 2-D Gaussian-like vMF of ``sigma_km`` plus a small
uniform floor, :meth:`ErrorModel.single`). The answer's ``p_correct`` becomes the posterior
``odds(pu) * LR / (1 + odds(pu) * LR)`` — a 100 m prior separates a winner 100 m from it from
a look-alike 450 m away (LR ~ e^10), while the verifier's fixed gate (``prior_gate`` 1e4)
never drops a competitor that close.

**Guard** (a prior that lies about its sigma must not create wrong fixes). The prior may weigh
in only when

1. the winner lies within ``CONSISTENT_SIGMAS`` (3) sigma of the prior: the answer is
   consistent with the prior's own region, and
2. geometry alone already prefers the winner: its inliers are above the noise level
   (the map's ``competitor_floor``: its matcher's noise level, at least 12) and ``pu >= 0.5`` (no
   far candidate holds as much evidence).

A prior 2 km off claiming 100 m either has no consistent winner (the true place is 20 sigma
away: rule 1, the answer is judged on geometry alone), or its winner is a wrong place near it
that geometry does not support (noise-level inliers, or the true place with more inliers
elsewhere: rule 2). Failing the guard, the prior adds nothing: ``p_correct`` is the
ungated ``pu`` (flag ``prior_inconsistent``), so the answer is a fix only when geometry alone is
decisive. docs/node.md "The robot's own estimate as a prior" has the measured effect.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.localization.fusion.error_model import ErrorModel
from vlm_vpr_ros.localization.verification.p_correct import verified_radius
from vlm_vpr_ros.localization.verification.evidence import EvidenceConfig
from vlm_vpr_ros.types import Hypothesis

#: the prior's region: the winner must lie within this many of its sigmas
CONSISTENT_SIGMAS = 3.0
#: geometry alone must prefer the winner at least this much (pu)
MIN_P_WITHOUT_PRIOR = 0.5
_EVIDENCE = EvidenceConfig()


def applies(hyp: Hypothesis, policy: Any) -> bool:
    """A verified answer whose trusted prior carries its own sigma."""
    p = hyp.prior
    return (p is not None and p.sigma_km is not None and p.sigma_km > 0
            and bool(getattr(policy, "trust_operator_prior", False))
            and math.isfinite(hyp.p_correct_without_prior) and bool(hyp.candidates)
            and hyp.inliers >= 0)


def weigh_trusted_prior(hyp: Hypothesis, model: Any = None, level: float = 0.95,
                        evidence: EvidenceConfig = _EVIDENCE) -> None:
    """Set ``hyp.p_correct`` from pu and the prior (module docstring), or to pu with the flag
    ``prior_inconsistent`` when the guard refuses the prior; with the verifier's calibration
    ``model``, narrow the radii for the new ``p_correct`` (never widen them). ``evidence``: the
    map's (its matcher's noise level and place radius)."""
    prior, pu = hyp.prior, hyp.p_correct_without_prior
    assert prior is not None and prior.sigma_km is not None
    d_win = float(haversine_km(prior.lat, prior.lon, hyp.lat, hyp.lon))
    consistent = d_win <= CONSISTENT_SIGMAS * prior.sigma_km
    supported = hyp.inliers > evidence.competitor_floor and pu >= MIN_P_WITHOUT_PRIOR
    if not (consistent and supported):
        hyp.p_correct = pu
        if "prior_inconsistent" not in hyp.flags:
            hyp.flags = tuple(hyp.flags) + ("prior_inconsistent",)
        return
    radius_km = evidence.place_radius_m / 1000.0
    far = [c for c in hyp.candidates
           if c.inliers is not None and c.inliers >= 0
           and float(haversine_km(hyp.lat, hyp.lon, c.lat, c.lon)) > radius_km]
    if not far:
        hyp.p_correct = pu
        return
    rival = max(far, key=lambda c: c.inliers)
    d_rival = float(haversine_km(prior.lat, prior.lon, rival.lat, rival.lon))
    own = ErrorModel.single(prior.sigma_km, name=prior.source)
    log_lr = np.diff(own.log_density(np.array([d_rival, d_win])))[0]
    pu = min(pu, 1.0 - 1e-12)
    log_odds = math.log(max(pu, 1e-12)) - math.log1p(-pu) + float(log_lr)
    hyp.p_correct = 1.0 / (1.0 + math.exp(-min(max(log_odds, -700.0), 700.0)))
    if model is not None:
        r68 = verified_radius(model, hyp.p_correct, 0.68, hyp.uncertainty_m, level)
        r95 = hyp.radius95_m if math.isfinite(hyp.radius95_m) else r68
        hyp.uncertainty_m = r68
        hyp.radius95_m = max(r68, verified_radius(model, hyp.p_correct, 0.95, r95, level))
