"""The matcher's noise level, measured per map on unrelated reference pairs (issue 42): the
competitor floor of the evidence is its 99th percentile, never below SIFT's 12."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vlm_vpr_ros.errors import MapError

from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.localization.verification.p_correct import (MIN_COMPETITOR_FLOOR,
                                                             NOISE_QUANTILE, noise_level,
                                                             noise_pairs, validate)


def _grid(n: int, step_deg: float) -> np.ndarray:
    return np.array([[37.0 + step_deg * i, -122.0] for i in range(n)])


def test_pairs_are_distinct_far_apart_and_reproducible():
    coords = _grid(40, 0.001)  # 111 m steps
    a = noise_pairs(coords, 50, 250.0, np.random.default_rng(3))
    b = noise_pairs(coords, 50, 250.0, np.random.default_rng(3))
    assert a == b and len(a) == 50
    assert len({(min(i, j), max(i, j)) for i, j in a}) == 50
    for i, j in a:
        d = float(haversine_km(*coords[i], *coords[j])) * 1000.0
        assert d >= 250.0 and i != j


def test_copies_of_one_photo_are_never_a_pair():
    coords = _grid(6, 0.01)  # 1.1 km steps: every pair is far enough
    twins = {0: (3,), 3: (0,), 1: (4,), 4: (1,)}  # the same photo at two places
    pairs = noise_pairs(coords, 100, 250.0, np.random.default_rng(1),
                        copies_of=lambda g: twins.get(g, ()))
    assert len(pairs) == 15 - 2  # every pair of 6 rows but the two copies
    assert not {(0, 3), (1, 4)} & {(min(i, j), max(i, j)) for i, j in pairs}


def test_no_pairs_on_a_map_smaller_than_the_distance():
    coords = _grid(30, 0.0001)  # 11 m steps: the whole map spans 322 m
    pairs = noise_pairs(coords, 20, 1000.0, np.random.default_rng(0))
    assert pairs == []
    assert noise_level([])["floor"] == MIN_COMPETITOR_FLOOR
    assert noise_pairs(_grid(1, 1.0), 5, 0.0, np.random.default_rng(0)) == []


def test_level_is_the_quantile_of_the_counts_with_the_minimum():
    rng = np.random.default_rng(7)
    counts = rng.integers(0, 60, 300)
    lv = noise_level(counts.tolist())
    srt = np.sort(counts)
    expect = int(srt[math.ceil(NOISE_QUANTILE * (len(srt) - 1))])  # the "higher" quantile
    assert lv["p99"] == expect and lv["floor"] == max(expect, MIN_COMPETITOR_FLOOR)
    assert lv["pairs"] == 300 and lv["max"] == int(counts.max())
    quiet = noise_level([0] * 290 + [9] * 10)
    assert quiet["p99"] == 9 and quiet["floor"] == MIN_COMPETITOR_FLOOR


def test_calibration_document_checks_the_floor():
    doc = {"format": "vlm_vpr_ros.verification_calibration", "version": 2,
           "null_scores": [0.5], "place_errors_m": [], "conditions": ["full"],
           "min_long_side_px": 0, "place_radius_m": 25.0, "top_k": 20,
           "protection": {"residual_m": 25.0, "integrity_risk": 1e-3}}
    for bad in (-1, 1.5, "12", True):
        with pytest.raises(MapError, match="competitor_floor"):
            validate({**doc, "competitor_floor": bad}, "verification.json")
    assert validate({**doc, "competitor_floor": 31}, "x")["competitor_floor"] == 31
