"""Balanced submaps: split every submap above a size cap into K-means sub-clusters of position.

Query time of a submap grows with its size, so one huge cluster or country (252k of 4.1M
references in a K=100 MP-16 map) sets the worst case. :func:`split_large` splits such a submap
into ``ceil(n / cap)`` pieces by K-means on the positions inside it, then halves any piece still
above the cap (a dense city) at the median of its widest axis, so no piece exceeds the cap;
pieces keep the parent as their ``group``. The localizer picks the country group first (country
maps), then the piece nearest to the prior; with K-means maps the nearest piece centroid is the
natural choice.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.geodesy import latlon_to_unit, unit_to_latlon
from vlm_vpr_ros.maps.partition import Partition, kmeans_positions

log = logging.getLogger(__name__)


def bisect(members: np.ndarray, xyz: np.ndarray, cap: int) -> list[np.ndarray]:
    """Split ``members`` at the median of their widest coordinate until every part holds at
    most ``cap`` (always terminates, even for references at one identical position)."""
    if len(members) <= cap:
        return [members]
    pts = xyz[members]
    axis = int(np.argmax(pts.max(0) - pts.min(0)))
    order = members[np.argsort(pts[:, axis], kind="stable")]
    half = len(order) // 2
    return bisect(np.sort(order[:half]), xyz, cap) + bisect(np.sort(order[half:]), xyz, cap)


def split_large(part: Partition, lat: np.ndarray, lon: np.ndarray, cap: int | None,
                seed: int = 0) -> tuple[Partition, list[str]]:
    """A partition whose submaps hold at most ~``cap`` references, and each submap's group
    (the submap it came from). ``cap`` None or 0: unchanged."""
    groups = list(part.names)
    if not cap:
        return part, groups
    if cap < 100:
        raise ConfigError(f"--max-submap-size must be >= 100, got {cap}")
    labels = np.full(len(part.labels), -1, dtype=np.int64)
    names: list[str] = []
    groups = []
    cents: list[tuple[float, float]] = []
    xyz = latlon_to_unit(lat, lon)
    for k, name in enumerate(part.names):
        sel = np.flatnonzero(part.labels == k)
        pieces = math.ceil(len(sel) / cap)
        if pieces <= 1:
            labels[sel] = len(names)
            names.append(name)
            groups.append(name)
            cents.append(tuple(part.centroids[k]))
            continue
        sub, _ = kmeans_positions(xyz[sel], pieces, seed, n_init=2)
        parts = []
        for j in range(pieces):  # K-means pieces of a dense city can still exceed the cap:
            parts += bisect(sel[sub == j], xyz, cap)  # halve those along their widest axis
        for j, members in enumerate(parts):
            if len(members) == 0:
                continue
            labels[members] = len(names)
            names.append(f"{name}.{j}")
            groups.append(name)
            c = xyz[members].mean(0)
            cla, clo = unit_to_latlon(c[None, :] / max(np.linalg.norm(c), 1e-12))
            cents.append((float(cla[0]), float(clo[0])))
        log.info("balanced submaps: %s (%d refs) split into %d pieces", name, len(sel),
                 len(parts))
    params = {**part.params, "max_submap_size": int(cap)}
    return Partition(part.method, labels, names, np.array(cents, dtype=np.float64).reshape(-1, 2),
                     params), groups
