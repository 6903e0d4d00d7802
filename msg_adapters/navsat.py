"""``sensor_msgs/NavSatFix`` from a :class:`~vlm_vpr_ros.types.Hypothesis`.

Policy (what ``robot_localization``'s navsat_transform expects):

* A full-method hypothesis (prior ok, match agrees with it) → ``STATUS_FIX``.
* A *flagged* hypothesis (no prior / prior failed / prior outside the map / match far from the
  prior: ``Hypothesis.flagged``) → ``STATUS_NO_FIX`` by default, with latitude/longitude still
  filled so people and loggers see the guess. navsat_transform skips NO_FIX messages, and its
  *first* accepted fix becomes the datum of the UTM→world transform, so a planet-scale global
  retrieval answer (possibly on the wrong continent) must not reach it silently. Users of
  city-scale maps, where global retrieval is as good as the prior-guided search, can choose
  ``fallback_status="fix"``; the covariance of a flagged fix is then at least
  ``fallback_min_sigma_m`` (default 25 km, the "city" accuracy level).
* Covariance: ENU, row-major, m², diagonal ``[σ², σ², σz²]`` with σ the core's
  ``uncertainty_m`` (always finite here), ``COVARIANCE_TYPE_APPROXIMATED``.
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


@dataclass(frozen=True)
class FixPolicy:
    fallback_status: str = "no_fix"  # "no_fix" or "fix"
    fallback_min_sigma_m: float = 25_000.0
    altitude_m: float = 0.0
    altitude_sigma_m: float = 1000.0


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


def finite_sigma(sigma_m: float) -> float:
    """Clamp a radius to (0, MAX_SIGMA_M]; non-finite or non-positive values become the max."""
    s = float(sigma_m)
    if not math.isfinite(s) or s <= 0.0:
        return MAX_SIGMA_M
    return min(s, MAX_SIGMA_M)


def fix_fields(hyp: Hypothesis, policy: FixPolicy | None = None) -> FixFields:
    """Status, covariance and position of the fix for ``hyp`` under ``policy``."""
    policy = policy or FixPolicy()
    sigma = finite_sigma(hyp.uncertainty_m)
    status = STATUS_FIX
    if hyp.flagged:
        sigma = finite_sigma(max(sigma, policy.fallback_min_sigma_m))
        status = STATUS_FIX if policy.fallback_status == "fix" else STATUS_NO_FIX
    var = sigma * sigma
    var_z = finite_sigma(policy.altitude_sigma_m) ** 2
    cov = (var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, var_z)
    return FixFields(float(hyp.lat), float(hyp.lon), float(policy.altitude_m), status, sigma,
                     cov, hyp.flagged)


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
