"""Building the ROS messages the bags carry (rclpy message objects), and finding a type's
rclpy class by its rosbag2 name."""

from __future__ import annotations

import importlib
import math
import re
from typing import Any

import numpy as np

from vlm_vpr_ros.errors import BagError

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
IMAGE_TYPES = (IMAGE, COMPRESSED)
_TYPE_NAME = re.compile(r"^([a-zA-Z][a-zA-Z0-9_]*)/(?:([a-zA-Z][a-zA-Z0-9_]*)/)?"
                        r"([a-zA-Z][a-zA-Z0-9_]*)$")


def message_class(type_name: str) -> Any:
    """The rclpy (rosidl Python) class of ``type_name`` (``sensor_msgs/msg/Image`` or
    ``sensor_msgs/Image``); BagError if its package is not installed."""
    m = _TYPE_NAME.match(type_name.strip())
    if not m:
        raise BagError(f"not a ROS 2 message type name: {type_name!r}")
    pkg, ns, name = m.group(1), m.group(2) or "msg", m.group(3)
    try:
        return getattr(importlib.import_module(f"{pkg}.{ns}"), name)
    except (ImportError, AttributeError) as exc:
        raise BagError(f"message type {type_name} is not available in this Python environment "
                       f"(install or source the '{pkg}' interface package): {exc}") from None


def split_stamp(t_ns: int) -> tuple[int, int]:
    return int(t_ns) // 1_000_000_000, int(t_ns) % 1_000_000_000


def stamp_ns(header: Any) -> int:
    """Nanoseconds of a message header's stamp."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _header(msg: Any, t_ns: int, frame_id: str) -> None:
    msg.header.stamp.sec, msg.header.stamp.nanosec = split_stamp(t_ns)
    msg.header.frame_id = frame_id


def image_msg(rgb: np.ndarray, t_ns: int, frame_id: str = "camera") -> Any:
    """``sensor_msgs/Image`` (rgb8) from an (H, W, 3) uint8 array."""
    from sensor_msgs.msg import Image

    h, w = rgb.shape[:2]
    msg = Image()
    _header(msg, t_ns, frame_id)
    msg.height, msg.width = int(h), int(w)
    msg.encoding = "rgb8"
    msg.is_bigendian = 0
    msg.step = int(w) * 3
    msg.data = np.ascontiguousarray(rgb, dtype=np.uint8).tobytes()
    return msg


def compressed_msg(data: bytes, fmt: str, t_ns: int, frame_id: str = "camera") -> Any:
    """``sensor_msgs/CompressedImage`` holding encoded bytes (``fmt``: "jpeg" or "png")."""
    from sensor_msgs.msg import CompressedImage

    msg = CompressedImage()
    _header(msg, t_ns, frame_id)
    msg.format = fmt
    msg.data = bytes(data)
    return msg


def navsatfix_msg(lat: float, lon: float, t_ns: int, frame_id: str = "gps",
                  sigma_m: float | None = None, fix: bool = True,
                  altitude: float = math.nan) -> Any:
    """``sensor_msgs/NavSatFix``; ``sigma_m`` fills a diagonal (approximated) covariance."""
    from sensor_msgs.msg import NavSatFix, NavSatStatus

    msg = NavSatFix()
    _header(msg, t_ns, frame_id)
    msg.status.status = NavSatStatus.STATUS_FIX if fix else NavSatStatus.STATUS_NO_FIX
    msg.status.service = NavSatStatus.SERVICE_GPS
    msg.latitude, msg.longitude, msg.altitude = float(lat), float(lon), float(altitude)
    if sigma_m is not None and math.isfinite(sigma_m):
        var = float(sigma_m) ** 2
        msg.position_covariance = [var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, var * 4.0]
        msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_APPROXIMATED
    else:
        msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_UNKNOWN
    return msg
