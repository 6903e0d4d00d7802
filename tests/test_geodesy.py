"""Haversine and accuracy tables against independently known values."""

import math

import numpy as np
import pytest

from vlm_vpr_ros.evaluation.metrics import errors_km, format_table, summarize
from vlm_vpr_ros.geodesy import (EARTH_RADIUS_KM, accuracy_table, enu_offset_m, haversine_km,
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


def test_enu_offset_small_displacement():
    east, north = enu_offset_m(0.0, 0.0, 0.001, 0.001)
    assert east == pytest.approx(111.195, abs=0.01) and north == pytest.approx(111.195, abs=0.01)
