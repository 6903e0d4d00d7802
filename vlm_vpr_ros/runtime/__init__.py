"""The node's query runtime without ROS: the parameter schema (:mod:`.params`), the latest-frame
worker (:mod:`.worker`) and its statistics for diagnostics (:mod:`.stats`). The ROS wiring is
:mod:`vlm_vpr_ros.ros`."""
