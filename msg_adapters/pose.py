"""``geometry_msgs/PoseWithCovarianceStamped`` from the pure
:class:`~vlm_vpr_ros.runtime.metric_frame.PoseFields` (frame, position, orientation, 6x6
covariance); the message class is imported inside the function."""

from __future__ import annotations

from typing import Any

from vlm_vpr_ros.runtime.metric_frame import PoseFields


def pose_with_covariance(fields: PoseFields, stamp_ns: int) -> Any:
    """A ``PoseWithCovarianceStamped`` (rclpy message) stamped ``stamp_ns``."""
    from geometry_msgs.msg import PoseWithCovarianceStamped

    msg = PoseWithCovarianceStamped()
    msg.header.stamp.sec = int(stamp_ns) // 1_000_000_000
    msg.header.stamp.nanosec = int(stamp_ns) % 1_000_000_000
    msg.header.frame_id = fields.frame_id
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = (float(v) for v in fields.position)
    q.x, q.y, q.z, q.w = (float(v) for v in fields.orientation)
    msg.pose.covariance = [float(v) for v in fields.covariance]
    return msg
