"""The status rule of an answer, pure (no ROS): used by the NavSatFix adapter, the results CSV,
the relocalize answer and diagnostics, so they all say the same.

``fix`` iff the answer was verified with ``p_correct >= fix_min_p_correct``, its protection
level is below ``fix_alert_limit_m`` and its per-axis σ is at most ``fix_max_sigma_m``; an
answer that reaches the threshold only because the prior removed far look-alikes from the
evidence (``prior_resolved``) is a fix only when the prior is trusted
(``trust_prior_for_fix``; ``trust_operator_prior`` for priors that carry their own
``sigma_km``, e.g. an operator's hint through the ``fixed`` provider). docs/verification.md.

Fallback: ``fallback_status="fix"`` publishes the answers failing the rule as ``fix`` too (for
filters that weigh every measurement by its covariance), with σ at least
``fallback_min_sigma_m``; :func:`stamp_status` decides it once per answer, so the NavSatFix,
the relocalize answer, diagnostics and results all carry the same status and σ (the reason
then starts with ``fallback:``).

σ: the per-axis σ of an isotropic 2-D Gaussian that holds at least the answer's 68 % and 95 %
radii and its protection level at the integrity risk, ``σ = max(r68 / 1.5096, r95 / 2.4477,
PL / 3.717)`` (Rayleigh quantiles; 3.717 = sqrt(-2 ln 1e-3)), always finite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.geodesy import MAX_DISTANCE_KM
from vlm_vpr_ros.types import Hypothesis

#: the largest σ ever published (half the Earth's circumference)
MAX_SIGMA_M = MAX_DISTANCE_KM * 1000.0
FALLBACK_STATUS = ("no_fix", "fix")
FALLBACK = "fallback: "  # status_reason of a fix published only by fallback_status="fix"
#: radius / σ of an isotropic 2-D Gaussian holding 68 % and 95 % of the mass (Rayleigh)
K68 = math.sqrt(-2.0 * math.log(0.32))
K95 = math.sqrt(-2.0 * math.log(0.05))
#: ... and all but 1e-3 (the integrity risk of the protection level, docs/verification.md)
K_RISK = math.sqrt(-2.0 * math.log(1e-3))


@dataclass(frozen=True)
class StatusPolicy:
    fix_min_p_correct: float = 0.99
    fix_max_sigma_m: float = 50.0
    trust_prior_for_fix: bool = False  # prior_resolved answers may be fixes (any prior)
    trust_operator_prior: bool = False  # ... when the prior carries its own sigma_km
    fallback_status: str = "no_fix"  # "fix": answers failing the rule are published as fixes
    fallback_min_sigma_m: float = 0.0  # ... with at least this σ (0: their own σ)
    #: a fix needs a protection level below this (m): the alert limit (docs/verification.md)
    fix_alert_limit_m: float = 50.0

    def __post_init__(self) -> None:
        if not (0.0 < self.fix_min_p_correct <= 1.0):
            raise ConfigError("fix_min_p_correct must be in (0, 1]")
        if not (self.fix_max_sigma_m > 0 and math.isfinite(self.fix_max_sigma_m)):
            raise ConfigError("fix_max_sigma_m must be a positive finite number")
        if self.fallback_status not in FALLBACK_STATUS:
            raise ConfigError(f"fallback_status must be one of {', '.join(FALLBACK_STATUS)}")
        if not (0.0 <= self.fallback_min_sigma_m <= MAX_SIGMA_M):
            raise ConfigError(f"fallback_min_sigma_m must be in [0, {MAX_SIGMA_M:g}]")
        a = self.fix_alert_limit_m
        if isinstance(a, bool) or not isinstance(a, (int, float)) or not (
                a > 0 and math.isfinite(a)):
            raise ConfigError(f"fix_alert_limit_m must be a positive finite number of metres, "
                              f"got {a!r}")

    def trusts(self, hyp: Hypothesis) -> bool:
        """Whether the answer's prior may resolve a fix."""
        if hyp.prior is None:
            return False
        return self.trust_prior_for_fix or (self.trust_operator_prior
                                            and hyp.prior.sigma_km is not None)


def k_risk(integrity_risk: float) -> float:
    """Radius / σ of an isotropic 2-D Gaussian that holds all but ``integrity_risk`` of its
    mass: ``sqrt(-2 ln risk)`` (3.72 at 1e-3)."""
    return math.sqrt(-2.0 * math.log(min(max(integrity_risk, 1e-300), 0.5)))


def finite_sigma(sigma_m: float) -> float:
    """Clamp to (0, MAX_SIGMA_M]; non-finite or non-positive values become the max."""
    s = float(sigma_m)
    if not math.isfinite(s) or s <= 0.0:
        return MAX_SIGMA_M
    return min(s, MAX_SIGMA_M)


def horizontal_sigma(hyp: Hypothesis) -> float:
    """Per-axis σ (m) of an answer from its 68 % / 95 % radii, and at least its protection
    level / :func:`k_risk` (1e-3): the Gaussian of the published covariance puts at most the
    integrity risk outside the protection level (module docstring)."""
    s = finite_sigma(hyp.uncertainty_m) / K68
    r95 = float(getattr(hyp, "radius95_m", math.nan))
    if math.isfinite(r95) and r95 > 0:
        s = max(s, finite_sigma(r95) / K95)
    pl = float(getattr(hyp, "protection_m", math.nan))
    if math.isfinite(pl) and pl > 0:
        s = max(s, pl / K_RISK)
    return finite_sigma(s)


def prior_resolved(hyp: Hypothesis, policy: StatusPolicy) -> bool:
    """The answer reaches ``fix_min_p_correct`` only with prior-gated competitors."""
    p, pu = hyp.p_correct, hyp.p_correct_without_prior
    return (hyp.prior is not None and math.isfinite(p) and p >= policy.fix_min_p_correct
            and not (math.isfinite(pu) and pu >= policy.fix_min_p_correct))


def fix_status(hyp: Hypothesis, policy: StatusPolicy | None = None) -> tuple[bool, str]:
    """(is a fix, why not) under ``policy`` (module docstring)."""
    policy = policy or StatusPolicy()
    if "no_match" in hyp.flags or not (math.isfinite(hyp.lat) and math.isfinite(hyp.lon)):
        return False, "no match"
    p = hyp.p_correct
    if not math.isfinite(p):
        return False, "unverified" if "unverified" in hyp.flags or not hyp.verification \
            else "uncalibrated verification"
    if p < policy.fix_min_p_correct:
        return False, f"p_correct {p:.3f} < {policy.fix_min_p_correct:g}"
    if prior_resolved(hyp, policy) and not policy.trusts(hyp):
        return False, "prior_resolved (the prior is not trusted for fixes)"
    pl = hyp.protection_m
    if not math.isfinite(pl):
        return False, "no protection level"
    if pl >= policy.fix_alert_limit_m:
        return False, f"protection {pl:.0f} m >= alert limit {policy.fix_alert_limit_m:g} m"
    sigma = horizontal_sigma(hyp)
    if sigma > policy.fix_max_sigma_m:
        return False, f"sigma {sigma:.0f} m > {policy.fix_max_sigma_m:g} m"
    return True, ""


def is_precise_fix(hyp: Hypothesis) -> bool:
    """A fix that passed the status rule (not one published by ``fallback_status: fix``): the
    answers that get a pose and a successful relocalize answer."""
    return hyp.status == "fix" and not hyp.status_reason.startswith(FALLBACK)


def stamp_status(hyp: Hypothesis, policy: StatusPolicy) -> Hypothesis:
    """Stamp ``status`` / ``status_reason`` (and the ``prior_resolved`` flag) on ``hyp`` under
    ``policy``, the fallback included (module docstring): the one decision every output uses."""
    if prior_resolved(hyp, policy) and "prior_resolved" not in hyp.flags:
        hyp.flags = tuple(hyp.flags) + ("prior_resolved",)
    ok, why = fix_status(hyp, policy)
    if not ok and policy.fallback_status == "fix" and why != "no match":
        least = policy.fallback_min_sigma_m
        if least > 0:  # widen the radii so that the published σ is at least ``least``
            r95 = hyp.radius95_m if math.isfinite(hyp.radius95_m) else 0.0
            hyp.uncertainty_m = max(hyp.uncertainty_m, least * K68)
            hyp.radius95_m = max(r95, least * K95)
        ok, why = True, FALLBACK + why
    hyp.status, hyp.status_reason = ("fix" if ok else "no_fix"), why
    return hyp
