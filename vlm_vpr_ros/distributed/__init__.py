"""Describing reference images at scale: descriptor shards, the local and the Ray engine.

``vlm-vpr describe`` and ``vlm-vpr build-map --engine ray`` live here (see docs/ray.md).
:mod:`~vlm_vpr_ros.distributed.shards` (the shard folder format) and
:mod:`~vlm_vpr_ros.distributed.describe` (the engine-independent job) never import Ray;
:mod:`~vlm_vpr_ros.distributed.ray_engine` imports it lazily, so the rest of the package runs
without it.
"""

ENGINES = ("local", "ray")
