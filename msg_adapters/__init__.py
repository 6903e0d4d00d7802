"""Conversions between ROS messages and the core's plain types.

The functions work on *field names only* (duck typing), so the same code serves rclpy message
objects, messages decoded from MCAP files (``mcap_ros2``) and ``rosbags`` dataclasses. Image
decoding never imports rclpy; the builders (:mod:`msg_adapters.navsat`,
:mod:`msg_adapters.diagnostics`) import the message classes lazily, inside the functions.
"""

from msg_adapters.image import (SUPPORTED_ENCODINGS, compressed_to_rgb, image_to_rgb,
                                message_to_rgb, stamp_ns)

__all__ = ["SUPPORTED_ENCODINGS", "compressed_to_rgb", "image_to_rgb", "message_to_rgb",
           "stamp_ns"]
