"""``sensor_msgs/NavSatFix`` from a :class:`~vlm_vpr_ros.types.Hypothesis`.

Policy (what ``robot_localization``'s navsat_transform expects; docs/fusion.md "NavSatFix"):

* The status follows the *calibrated quality* of the fix, not whether a prior was used:
  ``STATUS_FIX`` when the per-axis σ (below) is at most ``fix_max_sigma_m`` (default 50 m) and
  there was a match; otherwise ``STATUS_NO_FIX`` with latitude/longitude still filled so people
  and loggers see the guess. navsat_transform skips NO_FIX messages and its *first* accepted fix
  becomes the datum of the UTM→world transform, so only fixes that are known to be precise may
  reach it: a confident no-prior match is a fix with its real σ; a prior-guided guess with a
  wide posterior is not. ``fallback_status="fix"`` publishes the imprecise ones as STATUS_FIX
  too (their covariance then tells the filter how little to trust them), with σ at least
  ``fallback_min_sigma_m`` (default 0: the honest σ).
* Covariance: ENU, row-major, m², diagonal ``[σ², σ², σz²]``, ``COVARIANCE_TYPE_APPROXIMATED``,
  where σ is the per-axis σ of an isotropic 2-D Gaussian that holds at least the calibrated
  68 % and 95 % radii of the hypothesis: ``σ = max(r68 / 1.5096, r95 / 2.4477)`` (the Rayleigh
  quantiles), always finite.
* Altitude: images give none; NaN would make navsat_transform drop every fix, so a configurable
  finite value (default 0 m) with a large vertical σ (default 1000 m) is published.
* ``status.service`` is 0: no GNSS signal was used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from vlm_vpr_ros.geodesy import MAX_DISTANCE_KM
from vlm_vpr_ros.types import Hypothesis

STATUS_NO_FIX = -1
STATUS_FIX = 0
COVARIANCE_TYPE_APPROXIMATED = 1
#: the largest σ ever published (half the Earth's circumference)
MAX_SIGMA_M = MAX_DISTANCE_KM * 1000.0


#: radius / σ of an isotropic 2-D Gaussian holding 68 % and 95 % of the mass (Rayleigh)
K68 = math.sqrt(-2.0 * math.log(0.32))
K95 = math.sqrt(-2.0 * math.log(0.05))


@dataclass(frozen=True)
class FixPolicy:
    fallback_status: str = "no_fix"  # status of fixes failing the σ rule: "no_fix" or "fix"
    fallback_min_sigma_m: float = 0.0  # least σ of a fix failing the rule (0: its real σ)
    altitude_m: float = 0.0
    altitude_sigma_m: float = 1000.0
    fix_max_sigma_m: float = 50.0  # STATUS_FIX only when σ <= this


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
    precise: bool = True  # passed the σ rule for STATUS_FIX


def finite_sigma(sigma_m: float) -> float:
    """Clamp a radius to (0, MAX_SIGMA_M]; non-finite or non-positive values become the max."""
    s = float(sigma_m)
    if not math.isfinite(s) or s <= 0.0:
        return MAX_SIGMA_M
    return min(s, MAX_SIGMA_M)


def horizontal_sigma(hyp: Hypothesis) -> float:
    """Per-axis σ (m) of the fix from its calibrated 68 % / 95 % radii (module docstring)."""
    s = finite_sigma(hyp.uncertainty_m) / K68
    r95 = float(getattr(hyp, "radius95_m", math.nan))
    if math.isfinite(r95) and r95 > 0:
        s = max(s, finite_sigma(r95) / K95)
    return finite_sigma(s)


def fix_fields(hyp: Hypothesis, policy: FixPolicy | None = None) -> FixFields:
    """Status, covariance and position of the fix for ``hyp`` under ``policy``."""
    policy = policy or FixPolicy()
    sigma = horizontal_sigma(hyp)
    precise = (sigma <= policy.fix_max_sigma_m and "no_match" not in hyp.flags
               and math.isfinite(hyp.lat) and math.isfinite(hyp.lon))
    status = STATUS_FIX
    if not precise:
        sigma = finite_sigma(max(sigma, policy.fallback_min_sigma_m))
        status = (STATUS_FIX if policy.fallback_status == "fix" and "no_match" not in hyp.flags
                  else STATUS_NO_FIX)
    var = sigma * sigma
    var_z = finite_sigma(policy.altitude_sigma_m) ** 2
    cov = (var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, var_z)
    return FixFields(float(hyp.lat), float(hyp.lon), float(policy.altitude_m), status, sigma,
                     cov, hyp.flagged, precise)


def navsat_fix(hyp: Hypothesis, stamp_ns: int, frame_id: str,
               policy: FixPolicy | None = None) -> Any:
    """A ``sensor_msgs/NavSatFix`` (rclpy message) for ``hyp``, stamped ``stamp_ns``."""
    from sensor_msgs.msg import NavSatFix

    f = fix_fields(hyp, policy)
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
