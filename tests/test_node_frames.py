"""The pose output's metric frames (pure): UTM and local ENU against published coordinates,
the UTM zone rules, the covariance and orientation convention; the runtime-writable schema."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.runtime.metric_frame import (UNKNOWN_ANGLE_VAR, MetricFrame, metric_frame,
                                              utm_zone)
from vlm_vpr_ros.runtime.params import (PARAMETER_SPECS, RUNTIME_WRITABLE, from_params,
                                        refusal_reason)


@pytest.mark.parametrize("lat,lon,zone,east,north,tol", [
    # Wikipedia, "Universal Transverse Mercator coordinate system": the CN Tower,
    # 43°38′33.24″N 79°23′13.7″W, is at 17T 630084 m E 4833438 m N (rounded to 1 m)
    (43 + 38 / 60 + 33.24 / 3600, -(79 + 23 / 60 + 13.7 / 3600), 17, 630084.0, 4833438.0, 1.0),
    # the README of the `utm` package (PyPI): utm.from_latlon(51.2, 7.5) ->
    # (395201.3103811303, 5673135.241182375, 32, 'U')
    (51.2, 7.5, 32, 395201.3103811303, 5673135.241182375, 0.01),
])
def test_utm_matches_published_coordinates(lat, lon, zone, east, north, tol):
    assert utm_zone(lat, lon) == zone
    x, y, z = MetricFrame("utm").project(lat, lon, 12.5)
    assert abs(x - east) <= tol and abs(y - north) <= tol and z == 12.5


def test_utm_zone_rules_and_southern_hemisphere():
    assert utm_zone(0.0, -180.0) == 1 and utm_zone(0.0, 179.999) == 60
    assert utm_zone(0.0, 180.0) == 1  # the antimeridian wraps
    assert utm_zone(60.0, 4.0) == 32 and utm_zone(55.0, 4.0) == 31  # 32V is widened west
    assert [utm_zone(78.0, lon) for lon in (5.0, 10.0, 25.0, 40.0)] == [31, 33, 35, 37]
    # UTM is symmetric about the equator: the southern false northing is 10 000 km
    f = MetricFrame("utm")
    xn, yn, _ = f.project(33.9, 151.2, 0.0)
    xs, ys, _ = f.project(-33.9, 151.2, 0.0)
    assert xs == pytest.approx(xn, abs=1e-6) and ys == pytest.approx(10_000_000.0 - yn, abs=1e-6)
    # a fixed zone (navsat_transform keeps its datum's): the same point in the next zone west
    x32, _, _ = MetricFrame("utm", zone=32).project(51.2, 7.5, 0.0)
    x31, _, _ = MetricFrame("utm", zone=31).project(51.2, 7.5, 0.0)
    assert x31 > 800_000 > 500_000 > x32  # east of zone 31's central meridian, west of 32's
    with pytest.raises(ConfigError, match="outside UTM"):
        f.project(85.0, 10.0, 0.0)


def test_local_enu_matches_a_published_example_and_rotates():
    # MATLAB Mapping Toolbox, geodetic2enu: the Matterhorn (45.976, 7.658, 4531 m) seen from
    # Zermatt (46.017, 7.750, 1673 m) on WGS 84 is xEast -7134.8, yNorth -4556.3, zUp 2852.4.
    # Our datum's height is 0 (as navsat_transform's), which shifts only z by 1673 m.
    f = MetricFrame("local_enu", datum=(46.017, 7.750))
    x, y, z = f.project(45.976, 7.658, 4531.0)
    assert (x, y, z) == pytest.approx((-7134.8, -4556.3, 2852.4 + 1673.0), abs=0.1)
    # 1 km north of the datum, in a frame whose x axis points north (yaw +90 deg)
    lat1 = 46.017 + 1.0 / 111.2
    north = MetricFrame("local_enu", datum=(46.017, 7.750), yaw=math.pi / 2)
    xn, yn, _ = north.project(lat1, 7.750, 0.0)
    d = haversine_km(46.017, 7.750, lat1, 7.750) * 1000.0
    assert xn == pytest.approx(d, rel=5e-3) and abs(yn) < 1e-6
    with pytest.raises(ConfigError, match="datum"):
        MetricFrame("local_enu", datum=(math.nan, 7.0))
    assert metric_frame("none") is None


def test_pose_covariance_is_the_fix_covariance_and_heading_is_unknown():
    fix_cov = (900.0, 0.0, 0.0, 0.0, 900.0, 0.0, 0.0, 0.0, 1e6)
    pose = MetricFrame("utm", frame_id="utm").pose(39.5591, 8.8889, 0.0, fix_cov)
    c = np.asarray(pose.covariance).reshape(6, 6)
    assert c[0, 0] == c[1, 1] == 900.0 and c[0, 1] == c[1, 0] == 0.0 and c[2, 2] == 1e6
    assert c[5, 5] == c[3, 3] == c[4, 4] == UNKNOWN_ANGLE_VAR == pytest.approx(39.478, abs=1e-3)
    assert pose.orientation == (0.0, 0.0, 0.0, 1.0) and pose.frame_id == "utm"
    assert np.count_nonzero(c - np.diag(np.diag(c))) == 0
    # an anisotropic covariance is rotated into a rotated local frame: R C R^T
    yaw = 0.3
    aniso = (400.0, 50.0, 0.0, 50.0, 100.0, 0.0, 0.0, 0.0, 4.0)
    rot = MetricFrame("local_enu", "map", datum=(39.5, 8.8), yaw=yaw).pose(39.5, 8.8, 0.0, aniso)
    r = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]])
    want = r @ np.array([[400.0, 50.0], [50.0, 100.0]]) @ r.T
    got = np.asarray(rot.covariance).reshape(6, 6)[:2, :2]
    assert np.allclose(got, want) and rot.frame_id == "map"


def test_runtime_writable_parameters_and_refusal_reasons(tmp_path):
    assert {"fix_max_sigma_m", "fallback_status", "min_period_s", "top_p", "prior_timeout_s",
            "max_frame_age_s", "mode", "publish_debug", "pose_on"} <= RUNTIME_WRITABLE
    for structural in ("map_dir", "descriptor", "prior_provider", "qos", "subscribe_raw",
                       "fix_durability", "pose_frame", "datum_lat", "diagnostics_period_s"):
        assert PARAMETER_SPECS[structural].read_only and structural not in RUNTIME_WRITABLE
    assert "map_reload" in refusal_reason("map_dir") and "restart" in refusal_reason("map_dir")
    assert "prior provider" in refusal_reason("prior.model")
    assert "topics" in refusal_reason("qos") and "top_p" in refusal_reason("qos")
    # local_enu needs its datum; a datum is range-checked; map_dir may be checked later
    with pytest.raises(ConfigError, match="needs the parameter 'datum_lat'"):
        from_params({"map_dir": str(tmp_path), "pose_frame": "local_enu"})
    with pytest.raises(ConfigError, match="'datum_lon' must be in"):
        from_params({"map_dir": str(tmp_path), "datum_lon": 200.0})
    cfg = from_params({"map_dir": str(tmp_path / "later"), "pose_frame": "local_enu",
                       "datum_lat": 39.5, "datum_lon": 8.8}, check_paths=False)
    assert cfg.pose_frame == "local_enu" and math.isnan(from_params(
        {"map_dir": str(tmp_path)}).datum_lat)
