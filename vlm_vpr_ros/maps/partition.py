"""Splitting references into submaps: per country (reverse geocoding) or K-means on position."""

from __future__ import annotations

import contextlib
import logging
import sys
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.geodesy import haversine_km, latlon_to_unit, spherical_mean, unit_to_latlon

log = logging.getLogger(__name__)

PARTITION_METHODS = ("country", "kmeans", "none")
#: K-means on more positions than this is fitted on a random sample of this many
FIT_MAX = 200_000


@dataclass
class Partition:
    """Submap labels for N references: ``labels[i]`` indexes ``names``."""

    method: str
    labels: np.ndarray
    names: list[str]
    centroids: np.ndarray  # (K, 2) lat/lon per submap
    params: dict[str, Any] = field(default_factory=dict)


def country_codes(lat, lon) -> list[str]:
    """ISO 3166 alpha-2 code of the nearest populated place (offline, reverse_geocoder)."""
    import reverse_geocoder as rg

    pts = [(float(a), float(b)) for a, b in zip(np.atleast_1d(lat), np.atleast_1d(lon))]
    if not pts:
        return []
    # reverse_geocoder prints a loading banner on stdout; keep stdout clean for --json users.
    with contextlib.redirect_stdout(sys.stderr):
        res = rg.search(pts, mode=1, verbose=False)
    return [r["cc"] for r in res]


def _centroids(lat: np.ndarray, lon: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    return np.array([spherical_mean(lat[labels == i], lon[labels == i]) for i in range(k)])


def partition_country(lat: np.ndarray, lon: np.ndarray) -> Partition:
    codes = country_codes(lat, lon)
    names = sorted(set(codes))
    index = {c: i for i, c in enumerate(names)}
    labels = np.array([index[c] for c in codes], dtype=np.int64)
    return Partition("country", labels, names, _centroids(lat, lon, labels, len(names)))


def kmeans_positions(xyz: np.ndarray, k: int, seed: int = 0, n_init: int = 4,
                     fit_max: int = FIT_MAX) -> tuple[np.ndarray, np.ndarray]:
    """(labels int64, centres) of K-means on unit vectors (positions, :func:`latlon_to_unit`):
    fitted on a seeded sample of at most ``fit_max`` of them, then every point assigned to its
    nearest centre, so 4.1M positions cluster in seconds. K is clamped to the number of
    distinct points of the sample (KMeans needs at least K); empty clusters are possible
    (the caller drops them). The one K-means of the map partitions: :func:`partition_kmeans`
    and the balanced split (:mod:`vlm_vpr_ros.mapping.balance`)."""
    from sklearn.cluster import KMeans

    fit = xyz
    if len(xyz) > fit_max:
        fit = xyz[np.random.default_rng(seed).choice(len(xyz), fit_max, replace=False)]
    n_distinct = len(np.unique(np.round(fit, 9), axis=0))
    k_used = max(1, min(int(k), n_distinct))
    if k_used < k:
        log.info("kmeans: K clamped from %d to %d (distinct positions)", k, k_used)
    km = KMeans(n_clusters=k_used, n_init=n_init, random_state=seed).fit(fit)
    labels = km.labels_ if fit is xyz else km.predict(xyz)
    return labels.astype(np.int64), km.cluster_centers_


def partition_kmeans(lat: np.ndarray, lon: np.ndarray, clusters: int = 100,
                     seed: int = 0) -> Partition:
    """K-means on the positions (as unit vectors, so clusters may span the antimeridian).
    K is clamped to the number of distinct positions; empty clusters are dropped."""
    raw, centers = kmeans_positions(latlon_to_unit(lat, lon), clusters, seed)
    k = len(centers)
    used = np.unique(raw)
    remap = np.full(k, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    labels = remap[raw].astype(np.int64)
    cla, clo = unit_to_latlon(centers[used])
    names = [f"k{i:03d}" for i in range(len(used))]
    return Partition("kmeans", labels, names, np.stack([cla, clo], 1),
                     {"clusters": int(clusters), "effective_clusters": len(used), "seed": seed})


def partition_none(lat: np.ndarray, lon: np.ndarray) -> Partition:
    labels = np.zeros(len(lat), dtype=np.int64)
    return Partition("none", labels, ["all"], _centroids(lat, lon, labels, 1))


def make_partition(method: str, lat, lon, clusters: int = 100, seed: int = 0) -> Partition:
    lat, lon = np.asarray(lat, np.float64), np.asarray(lon, np.float64)
    fn = choose(method, {"country": partition_country, "kmeans": partition_kmeans,
                         "none": partition_none}, "partition method")
    if method == "kmeans":
        return fn(lat, lon, clusters, seed)
    return fn(lat, lon)


def nearest_centroids(lat: float, lon: float, centroids: np.ndarray, n: int = 1) -> np.ndarray:
    """Indices of the ``n`` submap centroids nearest to (lat, lon) by great-circle distance."""
    d = haversine_km(lat, lon, centroids[:, 0], centroids[:, 1])
    return np.argsort(np.atleast_1d(d), kind="stable")[:max(1, n)]
