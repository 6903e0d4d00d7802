"""An in-memory submap (built now, or loaded from a v1 map) and its geometry."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from vlm_vpr_ros.geodesy import farthest_km
from vlm_vpr_ros.maps import indexes


@dataclass
class Submap:
    """An in-memory submap (built now, or loaded from a v1 map). v2 maps load as
    :class:`vlm_vpr_ros.maps.store.LazySubmap`, which has the same attributes and methods."""

    id: str
    centroid: tuple[float, float]
    coords: np.ndarray  # (n, 2) float64
    ids: list[str]
    index: Any  # faiss.IndexFlatL2, fp16 IndexScalarQuantizer or IndexPQFastScan
    kind: str = "flat"  # flat | fp16 | pq (maps/indexes.py)
    rerank: np.ndarray | None = None  # pq: (n, dim) float16 re-rank vectors
    group: str = ""  # the submap this one was split from (balanced submaps); "" = itself
    recall: dict | None = None  # measured recall vs exact (approximate kinds)

    @property
    def count(self) -> int:
        return len(self.ids)

    def search(self, q: np.ndarray, k: int, factor: int) -> tuple[np.ndarray, np.ndarray]:
        return indexes.search(self.index, self.kind, self.rerank, q, k, factor)

    def searchable(self) -> Any:
        return self.index

    def pq_candidates(self, q: np.ndarray, kk: int) -> tuple[np.ndarray, np.ndarray]:
        return indexes.pq_candidates(self.index, q, kk)

    def exact_sq_l2(self, rows: np.ndarray, q: np.ndarray) -> np.ndarray:
        return indexes.exact_sq_l2(self.rerank, rows, q)

    def check_files(self, roles: tuple[str, ...] | None = None) -> None:
        """In memory: no files to check (see ``LazySubmap.check_files``)."""

    def prefetch(self, rows: np.ndarray, what: tuple[str, ...]) -> None:
        """In memory: nothing to read ahead (see ``LazySubmap.prefetch``)."""

    def vectors(self) -> np.ndarray:
        return indexes.vectors(self.index, self.kind, self.rerank)


def submap_radius_km(sub: Any) -> float:
    """Largest distance (km) from a submap's centroid to one of its references: stored in v2
    manifests (so opening a map reads no coordinates), computed for older maps."""
    stored = getattr(sub, "radius_km", None)
    if stored is not None:
        return float(stored)
    return farthest_km(sub.centroid[0], sub.centroid[1], sub.coords) if sub.count else 0.0
