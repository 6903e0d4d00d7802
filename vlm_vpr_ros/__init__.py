"""vlm_vpr_ros: VLM-guided visual place recognition for planet-scale geo-localization (ROS 2).

The localization core (this package minus :mod:`vlm_vpr_ros.node`) is pure Python: it never
imports rclpy, ROS message packages or mcap.
"""

__version__ = "0.1.0"
