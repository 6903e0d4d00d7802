"""``build-map --engine ray``: the local build's steps with describing, partitioning and index
building on Ray.

The map build itself is :func:`vlm_vpr_ros.mapping.build_images.build_map` (same up-to-date check,
fingerprint, skipped list, manifest and atomic save); this module only supplies its
``engine``: images are described into descriptor shards in the build's work folder
(``MAP/.build/shards``, resumable), read back from the shards, then the partition and the
per-submap FAISS indexes are built as Ray tasks.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.descriptors import GlobalDescriptor
from vlm_vpr_ros.distributed.describe import DescribeOptions, describe_to_shards
from vlm_vpr_ros.distributed.ray_engine import RaySession
from vlm_vpr_ros.distributed.shards import read_shards
from vlm_vpr_ros.mapping.build_images import build_map
from vlm_vpr_ros.mapping.image_sources import ImageSource
from vlm_vpr_ros.maps.reference_map import ReferenceMap

log = logging.getLogger(__name__)


class RayMapEngine:
    """The ``engine`` that ``build_map`` delegates to (see its docstring)."""

    def __init__(self, session: Any, opts: DescribeOptions) -> None:
        self.session, self.opts = session, opts
        self.result = None

    def describe(self, desc: GlobalDescriptor, images_dir, rows, work: Path,
                 progress: bool) -> tuple[np.ndarray, np.ndarray]:
        ids = [r[0] for r in rows]
        shards = Path(work) / "shards"
        source = ImageSource(images_dir)
        # the work folder is the build's own: a shard folder of other settings is replaced
        self.result = describe_to_shards(images_dir, ids, shards, descriptor=desc,
                                         options=self.opts, overwrite=True,
                                         engine=self.session.describer(source), staged=False)
        if self.result.described == 0:
            return np.zeros((len(ids), desc.dim), np.float32), np.zeros(len(ids), bool)
        return read_shards(shards, ids)

    def partition(self, method: str, lat, lon, clusters: int, seed: int):
        return self.session.partition(method, lat, lon, clusters, seed)

    def build_indexes(self, kind: str, dim: int, parts: list[np.ndarray]) -> list[Any]:
        return self.session.build_indexes(kind, dim, parts)


def build_map_ray(images_dir: str | Path, coords_csv: str | Path, out_dir: str | Path,
                  descriptor: str = "vlad_rootsift",
                  descriptor_config: Mapping[str, Any] | None = None,
                  partition: str = "kmeans", clusters: int = 100, overwrite: bool = False,
                  seed: int = 0, index: str = "flat",
                  options: DescribeOptions | None = None, local_features: str = "sift",
                  feature_options: Mapping[str, Any] | None = None,
                  matcher_options: Mapping[str, Any] | None = None) -> ReferenceMap:
    """``build_map`` with the Ray engine (starts a local Ray without ``ray_address``). The
    references' local features (``local_features``, docs/verification.md) are extracted by
    the driver after the Ray pass, in the build's resumable chunks."""
    opts = options or DescribeOptions(engine="ray")
    opts.engine = "ray"
    opts.validate()
    with RaySession(opts) as session:
        return build_map(images_dir, coords_csv, out_dir, descriptor=descriptor,
                         descriptor_config=descriptor_config, partition=partition,
                         clusters=clusters, overwrite=overwrite, progress=opts.progress,
                         seed=seed, index=index, engine=RayMapEngine(session, opts),
                         local_features=local_features, feature_options=feature_options,
                         matcher_options=matcher_options)
