"""Geodesy on the sphere of the geo-localization literature (mean Earth radius
:data:`EARTH_RADIUS_KM`): great-circle distances, destinations, accuracy tables.

Destinations and scalar distances are pyproj's ``Geod`` on that sphere (``a = b = R``:
Karney's geodesics, PROJ). Distances between *arrays* keep a vectorised numpy haversine, because
that is where the time goes (a query's candidates, a map's submap centroids, the build-time
calibrations over whole maps) and Geod is slower there: ``benchmarks/bench_geodesy.py``
printed, per call on the shared 2-core AMD EPYC at load ~19 (numpy / Geod): 1 pair 68.8 /
6.6 us, 50 pairs 57.4 / 137.8 us, 1,000 pairs 54.6 / 4335.5 us, 100,000 pairs 84 / 379 ms,
largest difference 1.6e-7 m. The radius is the one Earth-radius constant of the package; the
sphere (not the WGS-84 ellipsoid) keeps the accuracy thresholds comparable with the literature.
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np
from pyproj import Geod

#: mean Earth radius used by the geo-localization literature (km)
EARTH_RADIUS_KM = 6371.0088
#: pyproj's geodesics on the sphere of :data:`EARTH_RADIUS_KM`
_SPHERE = Geod(a=EARTH_RADIUS_KM * 1000.0, b=EARTH_RADIUS_KM * 1000.0)
#: the paper's accuracy thresholds (km)
THRESHOLDS_KM: tuple[float, ...] = (1.0, 25.0, 200.0, 750.0, 2500.0)
#: half the Earth's circumference: the largest possible great-circle error (km)
MAX_DISTANCE_KM = math.pi * EARTH_RADIUS_KM


def valid_latlon(lat: float, lon: float) -> bool:
    """True for finite WGS-84 degrees in range."""
    return (math.isfinite(lat) and math.isfinite(lon)
            and -90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0)


def haversine_km(lat1, lon1, lat2, lon2) -> np.ndarray | float:
    """Great-circle distance(s) in km; accepts scalars or broadcastable arrays (degrees);
    a float for scalars, else an array of the broadcast shape. NaN in, NaN out."""
    if all(isinstance(v, (int, float)) for v in (lat1, lon1, lat2, lon2)):
        if not all(math.isfinite(v) for v in (lat1, lon1, lat2, lon2)):
            return math.nan  # as the numpy path
        if abs(lat1) <= 90.0 and abs(lat2) <= 90.0:  # PROJ answers NaN beyond the poles
            return float(_SPHERE.inv(float(lon1), float(lat1), float(lon2),
                                     float(lat2))[2]) / 1e3
    return _numpy_haversine_km(lat1, lon1, lat2, lon2)


def _numpy_haversine_km(lat1, lon1, lat2, lon2) -> np.ndarray | float:
    """The vectorised haversine (arrays; module docstring)."""
    lat1, lon1, lat2, lon2 = (np.radians(np.asarray(v, dtype=np.float64))
                              for v in (lat1, lon1, lat2, lon2))
    a = (np.sin((lat2 - lat1) / 2.0) ** 2
         + np.cos(lat1) * np.cos(lat2) * np.sin((lon2 - lon1) / 2.0) ** 2)
    d = 2.0 * EARTH_RADIUS_KM * np.arcsin(np.sqrt(np.clip(a, 0.0, 1.0)))
    return float(d) if d.ndim == 0 else d


def farthest_km(lat: float, lon: float, coords: np.ndarray) -> float:
    """Great-circle distance (km) from (lat, lon) to the farthest of ``coords`` ((n, 2) lat,
    lon); 0 when there are none (a submap's radius around its centroid)."""
    c = np.asarray(coords, dtype=np.float64).reshape(-1, 2)
    return float(np.max(haversine_km(lat, lon, c[:, 0], c[:, 1]))) if len(c) else 0.0


def latlon_to_unit(lat, lon) -> np.ndarray:
    """(N, 3) unit vectors on the sphere for degrees lat/lon (for seam-free clustering)."""
    lat = np.radians(np.asarray(lat, dtype=np.float64))
    lon = np.radians(np.asarray(lon, dtype=np.float64))
    return np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], -1)


def unit_to_latlon(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`latlon_to_unit` (vectors need not be unit length)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    lat = np.degrees(np.arctan2(xyz[..., 2], np.hypot(xyz[..., 0], xyz[..., 1])))
    lon = np.degrees(np.arctan2(xyz[..., 1], xyz[..., 0]))
    return lat, lon


def spherical_mean(lat, lon) -> tuple[float, float]:
    """Centroid of points on the sphere (handles the antimeridian)."""
    la, lo = unit_to_latlon(latlon_to_unit(lat, lon).mean(axis=0))
    return float(la), float(lo)


def accuracy_table(errors_km: Iterable[float | None],
                   thresholds: Sequence[float] = THRESHOLDS_KM) -> dict[str, float]:
    """Percent of rows with error ≤ each threshold; ``None``/NaN rows count as misses."""
    errs = np.array([np.nan if e is None else float(e) for e in errors_km], dtype=np.float64)
    n = len(errs)
    out = {}
    for t in thresholds:
        hits = int(np.sum(np.nan_to_num(errs, nan=np.inf) <= t))
        out[f"{t:g}km"] = 100.0 * hits / n if n else 0.0
    return out


def median_km(errors_km: Iterable[float | None]) -> float | None:
    """Median error over rows, a missing row counting as the worst possible error."""
    errs = [MAX_DISTANCE_KM if e is None or not math.isfinite(e) else float(e)
            for e in errors_km]
    return float(np.median(errs)) if errs else None


def destination(lat: float, lon: float, distance_km: float,
                bearing_deg: float) -> tuple[float, float]:
    """The point ``distance_km`` from (lat, lon) along the great circle leaving at
    ``bearing_deg`` (clockwise from north); longitude wrapped to [-180, 180)."""
    lo2, la2, _ = _SPHERE.fwd(float(lon), float(lat), float(bearing_deg),
                              float(distance_km) * 1000.0)
    return float(la2), (float(lo2) + 540.0) % 360.0 - 180.0
