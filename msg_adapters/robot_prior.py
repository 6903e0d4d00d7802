"""The robot's own estimate (``prior_topic``) from ROS messages, for
:mod:`vlm_vpr_ros.priors.robot`: ``sensor_msgs/NavSatFix``, ``geometry_msgs/
PoseWithCovarianceStamped`` or ``nav_msgs/Odometry`` in the node's metric frame (``utm`` /
``local_enu``, :mod:`vlm_vpr_ros.runtime.metric_frame`). Field names only (duck typing);
``ConfigError`` says why a message cannot be used (the node logs it once and ignores it)."""

from __future__ import annotations

import math
from typing import Any

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.priors.robot import RobotEstimate, sigma_from_covariance
from vlm_vpr_ros.runtime.metric_frame import MetricFrame

KINDS = ("navsat", "pose", "odometry")
NAVSAT_NO_FIX = -1


def _stamp_s(header: Any) -> float:
    return int(header.stamp.sec) + int(header.stamp.nanosec) * 1e-9


def estimate_from_msg(kind: str, msg: Any, frame: MetricFrame | None,
                      source: str = "") -> RobotEstimate:
    """The estimate a message carries (stamp: the header's, seconds). ConfigError for a
    NavSatFix without a fix or without covariance, NaN / zero / negative covariance, or a
    pose in a frame the node cannot convert."""
    source = source or kind
    if kind == "navsat":
        if int(msg.status.status) <= NAVSAT_NO_FIX:
            raise ConfigError("NavSatFix has STATUS_NO_FIX")
        if int(msg.position_covariance_type) == 0:
            raise ConfigError("NavSatFix covariance type is UNKNOWN (no sigma)")
        c = msg.position_covariance
        sigma = sigma_from_covariance(float(c[0]), float(c[1]), float(c[4]))
        return RobotEstimate(float(msg.latitude), float(msg.longitude), sigma,
                             _stamp_s(msg.header), source)
    if kind not in ("pose", "odometry"):
        raise ConfigError(f"unknown prior_topic_type {kind!r}; choices: {', '.join(KINDS)}")
    pose = msg.pose  # PoseWithCovariance in both message types
    frame_id = str(msg.header.frame_id).lstrip("/")
    if frame is None:
        raise ConfigError(f"frame {frame_id!r}: the node has no metric frame (pose_frame none)")
    if frame_id != frame.frame_id:
        raise ConfigError(f"frame {frame_id!r} cannot be converted (the node knows "
                          f"{frame.frame_id!r}: pose_frame / pose_frame_id)")
    c = pose.covariance
    sigma = sigma_from_covariance(float(c[0]), float(c[1]), float(c[7]))
    p = pose.pose.position
    lat, lon = frame.unproject(float(p.x), float(p.y))
    if not (math.isfinite(lat) and math.isfinite(lon)):
        raise ConfigError("position has no WGS-84 equivalent")
    return RobotEstimate(lat, lon, sigma, _stamp_s(msg.header), source)


def message_class(kind: str) -> Any:
    """The ROS message class of a ``prior_topic_type``."""
    if kind == "navsat":
        from sensor_msgs.msg import NavSatFix
        return NavSatFix
    if kind == "pose":
        from geometry_msgs.msg import PoseWithCovarianceStamped
        return PoseWithCovarianceStamped
    if kind == "odometry":
        from nav_msgs.msg import Odometry
        return Odometry
    raise ConfigError(f"unknown prior_topic_type {kind!r}; choices: {', '.join(KINDS)}")
