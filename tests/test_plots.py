"""Plots: the numbers behind the figures, and that the PNGs are real images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vlm_vpr_ros.geodesy import THRESHOLDS_KM, accuracy_table
from vlm_vpr_ros.evaluation.plots import (_extent, cdf_percent, land_points, plot_error_cdf,
                                          plot_topp_ablation, plot_world_map)


def _png(path):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[0] > 200 and img.shape[1] > 400
    return img


def test_cdf_matches_accuracy_table():
    rng = np.random.default_rng(1)
    errs = list(rng.lognormal(4, 2.5, 300)) + [None, float("nan")]
    acc = accuracy_table(errs)
    assert cdf_percent(errs, THRESHOLDS_KM) == pytest.approx(
        [acc[f"{t:g}km"] for t in THRESHOLDS_KM])
    assert cdf_percent([], [1.0]).tolist() == [0.0]


def test_land_points_are_offline_and_plausible():
    pts = land_points()
    assert len(pts) > 100_000
    assert (np.abs(pts[:, 0]) <= 90).all() and (np.abs(pts[:, 1]) <= 180).all()


def test_extent_world_or_regional():
    world = np.array([[48.8, 2.3], [-33.9, 151.2]])
    assert _extent(world) == (-180.0, 180.0, -60.0, 85.0)
    atl = np.array([[33.774, -84.398], [33.776, -84.395]])
    lon0, lon1, lat0, lat1 = _extent(atl)
    assert lon0 < -84.398 and lon1 > -84.395 and lat0 < 33.774 and lat1 > 33.776
    assert lon1 - lon0 < 1.0


def test_world_map_draws_points(tmp_path):
    gt = [(48.85, 2.35), (35.68, 139.69), (-33.87, 151.21)]
    est = [(48.86, 2.34), None, (-37.81, 144.96)]
    pri = [(47.0, 3.0), (35.0, 135.0), None]
    img = _png(plot_world_map(tmp_path / "w.png", gt, est, pri, title="t"))
    red = (img[:, :, 2] > 180) & (img[:, :, 1] < 80) & (img[:, :, 0] < 80)
    green = (img[:, :, 1] > 120) & (img[:, :, 2] < 80) & (img[:, :, 0] < 120)
    assert red.sum() > 20 and green.sum() > 20
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write left no temp file


def test_cdf_and_topp_pngs(tmp_path):
    _png(plot_error_cdf(tmp_path / "c.png", {"a": [0.5, 30, None], "b": [3000.0]}, "x"))
    accs = [{f"{t:g}km": v for t in THRESHOLDS_KM} for v in (10.0, 20.0, 30.0)]
    _png(plot_topp_ablation(tmp_path / "t.png", [1, 10, 100], {"r1": accs, "r2": accs[::-1]}))
