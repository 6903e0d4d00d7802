"""``sensor_msgs/NavSatFix`` from a :class:`~vlm_vpr_ros.types.Hypothesis`.

Policy (what ``robot_localization``'s navsat_transform expects; docs/verification.md):

* The status is the one the pipeline stamped on the answer (``hyp.status``, under the status
  policy the query ran with), so the NavSatFix, the results CSV, the relocalize answer and
  diagnostics always agree; an answer without one is judged here by the same rule
  (:func:`vlm_vpr_ros.localization.verification.status.fix_status`):
  ``STATUS_FIX`` only for a *verified* answer with ``p_correct >= fix_min_p_correct`` (default
  0.95), a protection level below ``fix_alert_limit_m`` (default 50 m) and per-axis σ <=
  ``fix_max_sigma_m`` (default 50 m); an answer decisive only because
  the prior removed far look-alikes (``prior_resolved``) only when the prior is trusted
  (``trust_prior_for_fix`` / ``trust_operator_prior``). Everything else is ``STATUS_NO_FIX``
  with latitude/longitude still filled so people and loggers see the guess. navsat_transform
  skips NO_FIX messages and its *first* accepted fix becomes the datum of the UTM→world
  transform, so only fixes known to be right may reach it. ``fallback_status="fix"``
  publishes the others as STATUS_FIX too (their covariance then tells the filter how little
  to trust them), with σ at least ``fallback_min_sigma_m`` (default 0: the honest σ); the
  pipeline stamps that decision on the answer (``stamp_status``), so the relocalize answer and
  diagnostics say the same.
* Covariance: ENU, row-major, m², diagonal ``[σ², σ², σz²]``, ``COVARIANCE_TYPE_APPROXIMATED``,
  σ = ``max(r68 / 1.5096, r95 / 2.4477, PL / 3.717)`` of the answer's radii and its protection
  level PL (3.717 = sqrt(-2 ln 1e-3): the Gaussian of the covariance holds the PL's 1 - 1e-3;
  a verified fix: tens of metres; an unverified answer: the posterior's radius), always finite.
* Altitude: images give none; NaN would make navsat_transform drop every fix, so a configurable
  finite value (default 0 m) with a large vertical σ (default 1000 m) is published.
* ``status.service`` is 0: no GNSS signal was used.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from vlm_vpr_ros.localization.verification.status import (K68, K95, MAX_SIGMA_M,
                                                          StatusPolicy, finite_sigma,
                                                          horizontal_sigma, is_precise_fix,
                                                          stamp_status)
from vlm_vpr_ros.types import Hypothesis

__all__ = ["COVARIANCE_TYPE_APPROXIMATED", "FixFields", "FixPolicy", "K68", "K95",
           "MAX_SIGMA_M", "STATUS_FIX", "STATUS_NO_FIX", "finite_sigma", "fix_fields",
           "horizontal_sigma", "navsat_fix"]

STATUS_NO_FIX = -1
STATUS_FIX = 0
COVARIANCE_TYPE_APPROXIMATED = 1


@dataclass(frozen=True)
class FixPolicy:
    altitude_m: float = 0.0
    altitude_sigma_m: float = 1000.0
    #: the status rule (and its fallback) for answers the pipeline did not stamp
    status: StatusPolicy = field(default_factory=StatusPolicy)


@dataclass(frozen=True)
class FixFields:
    """The numbers of a NavSatFix, independent of any ROS message class."""

    latitude: float
    longitude: float
    altitude: float
    status: int
    sigma_m: float
    covariance: tuple[float, ...]  # 9 values, row-major ENU, m²
    flagged: bool
    precise: bool = True  # passed the status rule for STATUS_FIX
    reason: str = ""  # why not (status rule)


def fix_fields(hyp: Hypothesis, policy: FixPolicy | None = None) -> FixFields:
    """Status, covariance and position of the fix for ``hyp``: the status the pipeline stamped
    (one decision per answer, fallback included), or ``policy.status`` applied to a copy."""
    policy = policy or FixPolicy()
    if hyp.status not in ("fix", "no_fix"):
        hyp = stamp_status(dataclasses.replace(hyp), policy.status)
    sigma = horizontal_sigma(hyp)
    fix = hyp.status == "fix"
    precise = is_precise_fix(hyp)
    var = sigma * sigma
    var_z = finite_sigma(policy.altitude_sigma_m) ** 2
    cov = (var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, var_z)
    return FixFields(float(hyp.lat), float(hyp.lon), float(policy.altitude_m),
                     STATUS_FIX if fix else STATUS_NO_FIX, sigma, cov, hyp.flagged, precise,
                     hyp.status_reason)


def navsat_fix(hyp: Hypothesis, stamp_ns: int, frame_id: str,
               policy: FixPolicy | None = None, fields: FixFields | None = None) -> Any:
    """A ``sensor_msgs/NavSatFix`` (rclpy message) for ``hyp``, stamped ``stamp_ns``
    (``fields``: :func:`fix_fields` already computed for it)."""
    from sensor_msgs.msg import NavSatFix

    f = fields if fields is not None else fix_fields(hyp, policy)
    msg = NavSatFix()
    msg.header.stamp.sec = int(stamp_ns) // 1_000_000_000
    msg.header.stamp.nanosec = int(stamp_ns) % 1_000_000_000
    msg.header.frame_id = frame_id
    msg.status.status = f.status
    msg.status.service = 0
    msg.latitude, msg.longitude, msg.altitude = f.latitude, f.longitude, f.altitude
    msg.position_covariance = [float(v) for v in f.covariance]
    msg.position_covariance_type = COVARIANCE_TYPE_APPROXIMATED
    return msg
