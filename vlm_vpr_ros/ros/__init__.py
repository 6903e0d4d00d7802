"""The ROS 2 edge: ``vlm_vpr_node`` / ``vlm_vpr_lifecycle_node`` (:mod:`.node`) and the wiring
they share (:mod:`.wiring`). The only part of the package that imports rclpy."""
