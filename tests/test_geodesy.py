"""Haversine and accuracy tables against independently known values."""

import math

import numpy as np
import pytest

from vlm_vpr_ros.evaluation.metrics import errors_km, format_table, summarize
from vlm_vpr_ros.geodesy import (EARTH_RADIUS_KM, accuracy_table, destination, haversine_km,
                                 median_km, spherical_mean)


@pytest.mark.parametrize("a,b,expected_km,tol", [
    ((0.0, 0.0), (0.0, 1.0), 2 * math.pi * EARTH_RADIUS_KM / 360, 1e-9),  # 1 deg on equator
    ((0.0, 0.0), (0.0, 180.0), math.pi * EARTH_RADIUS_KM, 1e-6),  # antipodes
    ((90.0, 0.0), (-90.0, 0.0), math.pi * EARTH_RADIUS_KM, 1e-6),  # pole to pole
    ((48.8566, 2.3522), (51.5074, -0.1278), 343.5, 0.6),  # Paris - London (published ~343.5)
    # Rosetta Code's haversine task: BNA-LAX = 2887.2599506071106 km with R = 6372.8 km
    ((36.12, -86.67), (33.94, -118.40), 2887.2599506071106 * EARTH_RADIUS_KM / 6372.8, 1e-6),
    ((-33.8688, 151.2093), (-36.8485, 174.7633), 2156.0, 5.0),  # Sydney - Auckland (~2156)
    ((0.0, 179.5), (0.0, -179.5), 2 * math.pi * EARTH_RADIUS_KM / 360, 1e-9),  # antimeridian
])
def test_haversine_known_distances(a, b, expected_km, tol):
    assert haversine_km(*a, *b) == pytest.approx(expected_km, abs=tol)
    assert haversine_km(*b, *a) == pytest.approx(expected_km, abs=tol)


def test_haversine_vectorised_matches_scalar():
    rng = np.random.default_rng(0)
    lat1, lat2 = rng.uniform(-90, 90, (2, 50))
    lon1, lon2 = rng.uniform(-180, 180, (2, 50))
    vec = haversine_km(lat1, lon1, lat2, lon2)
    assert vec.shape == (50,)
    for i in range(50):
        assert vec[i] == pytest.approx(haversine_km(lat1[i], lon1[i], lat2[i], lon2[i]))


def test_accuracy_table_counts_misses_and_thresholds_inclusive():
    errs = [0.5, 1.0, 24.9, 300.0, None, float("nan"), 2600.0, 2500.0]
    acc = accuracy_table(errs)
    n = len(errs)
    assert acc == {"1km": 100 * 2 / n, "25km": 100 * 3 / n, "200km": 100 * 3 / n,
                   "750km": 100 * 4 / n, "2500km": 100 * 5 / n}


def test_median_counts_missing_as_worst():
    assert median_km([1.0, 2.0, 3.0]) == 2.0
    assert median_km([1.0, None, None]) == pytest.approx(math.pi * EARTH_RADIUS_KM)
    assert median_km([]) is None


def test_summarize_shape_and_errors():
    est = [(48.8566, 2.3522), None, (0.0, 0.0)]
    gt = [(48.8566, 2.3522), (10.0, 10.0), (0.0, 1.0)]
    errs = errors_km(est, gt)
    assert errs[0] == 0.0 and errs[1] is None and errs[2] == pytest.approx(111.195, abs=0.01)
    s = summarize(errs)
    assert set(s) == {"n", "accuracy", "median_km"} and s["n"] == 3
    assert s["accuracy"]["1km"] == pytest.approx(33.33, abs=0.01)
    assert s["accuracy"]["200km"] == pytest.approx(66.67, abs=0.01)
    assert "66.67%" in format_table({"x": s})


def test_spherical_mean_handles_antimeridian():
    lat, lon = spherical_mean([10.0, 10.0], [179.0, -179.0])
    assert abs(abs(lon) - 180.0) < 1e-6 and lat == pytest.approx(10.0, abs=0.01)


def _cosine_law_km(lat1, lon1, lat2, lon2):
    """An independent great-circle distance (spherical law of cosines, float64)."""
    p1, p2, dl = np.radians(lat1), np.radians(lat2), np.radians(np.subtract(lon2, lon1))
    c = np.sin(p1) * np.sin(p2) + np.cos(p1) * np.cos(p2) * np.cos(dl)
    return EARTH_RADIUS_KM * np.arccos(np.clip(c, -1.0, 1.0))


def test_scalar_geod_and_array_haversine_paths_agree():
    """Scalars go through pyproj.Geod, arrays through the numpy haversine: the same distances
    (to a micrometre) and both equal an independent formula away from its ill-conditioned
    small angles; NaN in, NaN out on both paths."""
    rng = np.random.default_rng(3)
    la1, la2 = rng.uniform(-89, 89, (2, 200))
    lo1, lo2 = rng.uniform(-180, 180, (2, 200))
    arr = haversine_km(la1, lo1, la2, lo2)
    scal = np.array([haversine_km(float(a), float(b), float(c), float(d))
                     for a, b, c, d in zip(la1, lo1, la2, lo2)])
    assert isinstance(haversine_km(1.0, 2.0, 3.0, 4.0), float)
    assert np.max(np.abs(arr - scal)) < 1e-9
    assert np.max(np.abs(arr - _cosine_law_km(la1, lo1, la2, lo2))) < 1e-4
    assert math.isnan(haversine_km(math.nan, 0.0, 1.0, 1.0))
    # beyond the poles (invalid input, flagged by callers) both paths give the same number
    assert haversine_km(91.0, 0.0, 0.0, 0.0) == pytest.approx(
        float(haversine_km(np.array([91.0]), 0.0, 0.0, 0.0)[0]), rel=1e-12)
    assert np.isnan(haversine_km(np.array([np.nan, 0.0]), 0.0, 1.0, 1.0)[0])


@pytest.mark.parametrize("lat,lon,km,bearing", [(48.85, 2.35, 5000.0, 77.0),
                                                (-33.9, 151.2, 1234.5, 200.0),
                                                (10.0, 179.9, 300.0, 90.0), (0.0, 0.0, 0.01, 0.0)])
def test_destination_lies_at_the_distance_and_bearing(lat, lon, km, bearing):
    la2, lo2 = destination(lat, lon, km, bearing)
    assert -180.0 <= lo2 < 180.0
    assert float(_cosine_law_km(lat, lon, la2, lo2)) == pytest.approx(km, rel=1e-6, abs=1e-6)
    # initial bearing of the great circle to the destination (independent formula)
    p1, p2, dl = map(math.radians, (lat, la2, lo2 - lon))
    b = math.degrees(math.atan2(math.sin(dl) * math.cos(p2),
                                math.cos(p1) * math.sin(p2)
                                - math.sin(p1) * math.cos(p2) * math.cos(dl))) % 360.0
    assert min(abs(b - bearing), 360.0 - abs(b - bearing)) < 1e-6
