"""The fix in a metric frame, for the node's ``pose`` output (pure: no ROS).

Two frames, the ones robot_localization's navsat_transform names when it broadcasts its
cartesian transform (``broadcast_cartesian_transform``):

* ``utm``: WGS 84 / UTM, easting and northing in metres (EPSG:326zz north, 327zz south). The
  zone is the fix's own (standard zones with the Norway 32V and Svalbard 31X-37X exceptions,
  as GeographicLib's ``UTMUPS::StandardZone``) or a fixed one (``utm_zone``): navsat_transform
  keeps the zone of its datum, so a robot near a zone border should fix it. UTM covers
  latitudes -80..84; outside them (UPS) no pose is made. A fixed zone serves fixes up to
  :data:`MAX_ZONE_OFFSET_DEG` of longitude from its central meridian (two zone widths: the
  scale error of the projection stays under 2.2 %); a fix farther away (a wrong fix, or the
  wrong zone configured) gets no pose, with the reason, not finite nonsense.
* ``local_enu``: the tangent plane at a datum (latitude, longitude, height 0 on the
  ellipsoid; GeographicLib's ``LocalCartesian`` used by navsat_transform's
  ``use_local_cartesian``), rotated by ``datum_yaw`` (the frame's x axis, counter-clockwise
  from east) so that it can be a robot's ``map`` frame. A tangent plane is a local frame: a fix
  more than :data:`MAX_LOCAL_KM` from the datum (the plane is then ~20 km below the ground)
  gets no pose, with the reason.

Projections are PROJ's (pyproj: ``+proj=utm``, ``+proj=cart`` + ``+proj=topocentric``), not
hand-written series. The pose's covariance is the fix's horizontal covariance rotated into the
frame (unchanged for the isotropic covariance the node publishes; UTM's grid convergence is not
applied, the covariance being isotropic), the altitude variance on z, and an unknown
orientation: identity quaternion with roll, pitch and yaw variance ``(2 pi)^2``, so a wrapped
Gaussian on the angle is uniform within 1e-8 (AMCL spreads its particles over every heading; a
filter treats the heading as unknown).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.geodesy import haversine_km

KINDS = ("utm", "local_enu", "none")
#: variance of an unknown angle (rad^2): sigma of a full turn
UNKNOWN_ANGLE_VAR = (2.0 * math.pi) ** 2
UTM_LAT_RANGE = (-80.0, 84.0)
#: a fixed ``utm_zone`` serves fixes up to this far (degrees of longitude) from its meridian
MAX_ZONE_OFFSET_DEG = 12.0
#: a ``local_enu`` frame serves fixes up to this far (km) from its datum
MAX_LOCAL_KM = 500.0


def utm_zone(lat: float, lon: float) -> int:
    """The standard UTM zone of a position (1-60), with the Norway and Svalbard exceptions.

    Hand-written: six lines of published rules (the zone definitions of UTM); pyproj offers
    them only through a database query per call.
    """
    lon = ((lon + 180.0) % 360.0) - 180.0
    zone = min(int((lon + 180.0) // 6.0) + 1, 60)
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        return 32  # southwest Norway: zone 32V is widened west
    if 72.0 <= lat <= 84.0 and 0.0 <= lon < 42.0:  # Svalbard: 31X, 33X, 35X, 37X only
        return 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    return zone


@dataclass(frozen=True)
class PoseFields:
    """A pose with covariance, independent of any ROS message class."""

    frame_id: str
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]  # x, y, z, w
    covariance: tuple[float, ...]  # 36 values, row-major (x, y, z, roll, pitch, yaw)


class MetricFrame:
    """Converts fixes to one metric frame (``kind`` utm or local_enu); see the module doc."""

    def __init__(self, kind: str, frame_id: str = "", zone: int = 0,
                 datum: tuple[float, float] | None = None, yaw: float = 0.0) -> None:
        if kind not in KINDS[:2]:
            raise ConfigError(f"unknown metric frame {kind!r}; choices: {', '.join(KINDS)}")
        if not 0 <= int(zone) <= 60:
            raise ConfigError(f"UTM zone must be 0 (the fix's own) or 1-60, got {zone}")
        if kind == "local_enu" and (datum is None or not all(map(math.isfinite, datum))):
            raise ConfigError("a local_enu frame needs its datum (latitude, longitude)")
        self.kind, self.zone, self.datum, self.yaw = kind, int(zone), datum, float(yaw)
        self.frame_id = frame_id or kind
        self._transformers: dict[Any, Any] = {}

    def _transformer(self, key: Any) -> Any:
        tr = self._transformers.get(key)
        if tr is None:
            from pyproj import Transformer

            if self.kind == "utm":
                zone, north = key
                epsg = (32600 if north else 32700) + zone
                tr = Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)
            else:
                lat0, lon0 = self.datum  # type: ignore[misc]
                tr = Transformer.from_pipeline(
                    "+proj=pipeline +step +proj=cart +ellps=WGS84 +step +proj=topocentric "
                    f"+ellps=WGS84 +lat_0={lat0!r} +lon_0={lon0!r} +h_0=0")
            self._transformers[key] = tr
        return tr

    def project(self, lat: float, lon: float, alt: float) -> tuple[float, float, float]:
        """(x, y, z) of a position in this frame (m). ConfigError when it has none here."""
        if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt)):
            raise ConfigError("no metric position for a non-finite fix")
        if self.kind == "utm":
            lo, hi = UTM_LAT_RANGE
            if not lo <= lat <= hi:
                raise ConfigError(f"latitude {lat:.4f} is outside UTM ({lo:g}..{hi:g}); use "
                                  "pose_frame local_enu there")
            zone = self.zone or utm_zone(lat, lon)
            off = abs(((lon - (zone * 6.0 - 183.0)) + 180.0) % 360.0 - 180.0)
            if off > MAX_ZONE_OFFSET_DEG:
                raise ConfigError(f"longitude {lon:.4f} is {off:.1f} deg from the central "
                                  f"meridian of the fixed UTM zone {zone} (more than "
                                  f"{MAX_ZONE_OFFSET_DEG:g}): no pose; a wrong fix, or set "
                                  "utm_zone 0 (the fix's own zone)")
            x, y = self._transformer((zone, lat >= 0.0)).transform(lon, lat)
            return float(x), float(y), float(alt)
        lat0, lon0 = self.datum  # type: ignore[misc]
        km = float(haversine_km(lat0, lon0, lat, lon))
        if km > MAX_LOCAL_KM:
            raise ConfigError(f"the fix ({lat:.4f}, {lon:.4f}) is {km:.0f} km from the "
                              f"local_enu datum (more than {MAX_LOCAL_KM:g} km): no pose; a "
                              "wrong fix, or the datum of another place")
        e, n, u = self._transformer("enu").transform(lon, lat, alt)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return c * e + s * n, -s * e + c * n, float(u)

    def unproject(self, x: float, y: float) -> tuple[float, float]:
        """(lat, lon) of a point (x, y) of this frame: the inverse of :meth:`project` (a
        robot's own pose as a prior, :mod:`vlm_vpr_ros.priors.robot`). UTM needs a fixed
        zone (``utm_zone`` 1-60; the hemisphere is the datum's, north without one):
        ConfigError otherwise, or for non-finite coordinates."""
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ConfigError("no position for non-finite metric coordinates")
        if self.kind == "utm":
            if not self.zone:
                raise ConfigError("a UTM position needs a fixed zone to be converted (set "
                                  "utm_zone 1-60, the zone of navsat_transform's datum)")
            north = self.datum is None or not math.isfinite(self.datum[0]) or self.datum[0] >= 0
            lon, lat = self._transformer((self.zone, north)).transform(
                x, y, direction="INVERSE")
        else:
            c, s = math.cos(self.yaw), math.sin(self.yaw)  # inverse of R = [[c, s], [-s, c]]
            e, n = c * x - s * y, s * x + c * y
            lon, lat, _ = self._transformer("enu").transform(e, n, 0.0, direction="INVERSE")
        lat, lon = float(lat), float(lon)
        if not (math.isfinite(lat) and math.isfinite(lon) and -90 <= lat <= 90):
            raise ConfigError(f"({x:.1f}, {y:.1f}) in {self.frame_id} has no WGS-84 position")
        return lat, ((lon + 180.0) % 360.0) - 180.0

    def pose(self, lat: float, lon: float, alt: float,
             enu_covariance: tuple[float, ...]) -> PoseFields:
        """The pose of a fix: ``enu_covariance`` is the fix's 3x3 ENU covariance (row-major,
        NavSatFix ``position_covariance``)."""
        x, y, z = self.project(lat, lon, alt)
        cxx, cxy, cyy = enu_covariance[0], enu_covariance[1], enu_covariance[4]
        if self.kind == "local_enu" and self.yaw:
            c, s = math.cos(self.yaw), math.sin(self.yaw)  # R = [[c, s], [-s, c]]: R C R^T
            cxx, cxy, cyy = (c * c * cxx + 2 * c * s * cxy + s * s * cyy,
                             (c * c - s * s) * cxy + c * s * (cyy - cxx),
                             s * s * cxx - 2 * c * s * cxy + c * c * cyy)
        cov = [0.0] * 36
        cov[0], cov[1], cov[6], cov[7] = cxx, cxy, cxy, cyy
        cov[14] = enu_covariance[8]
        cov[21] = cov[28] = cov[35] = UNKNOWN_ANGLE_VAR
        return PoseFields(self.frame_id, (x, y, z), (0.0, 0.0, 0.0, 1.0), tuple(cov))


def metric_frame(kind: str, frame_id: str = "", zone: int = 0, datum_lat: float = math.nan,
                 datum_lon: float = math.nan, yaw: float = 0.0) -> MetricFrame | None:
    """The frame the node's parameters ask for (None for ``kind`` none)."""
    if kind == "none":
        return None
    return MetricFrame(kind, frame_id, zone, (datum_lat, datum_lon), yaw)
