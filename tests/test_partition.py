"""Submap assignment checked independently: countries of known cities, K-means membership."""

import numpy as np
import pytest

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.geodesy import haversine_km, latlon_to_unit
from vlm_vpr_ros.maps.partition import country_codes, make_partition, nearest_centroids


def test_country_codes_of_known_cities():
    cities = [(48.8566, 2.3522, "FR"), (35.6762, 139.6503, "JP"), (-1.2921, 36.8219, "KE"),
              (-23.5505, -46.6333, "BR"), (-33.8688, 151.2093, "AU"), (37.7749, -122.4194, "US"),
              (55.7558, 37.6173, "RU"), (30.0444, 31.2357, "EG")]
    codes = country_codes([c[0] for c in cities], [c[1] for c in cities])
    assert codes == [c[2] for c in cities]


def test_country_partition_groups_by_code(capsys):
    lat = [48.85, 48.9, 35.68, 43.6]
    lon = [2.35, 2.3, 139.65, 1.44]
    p = make_partition("country", lat, lon)
    assert p.names == ["FR", "JP"]
    assert list(p.labels) == [0, 0, 1, 0]
    assert capsys.readouterr().out == ""  # reverse_geocoder's banner must not reach stdout


def test_kmeans_membership_is_nearest_centroid():
    rng = np.random.default_rng(0)
    lat = rng.uniform(-60, 70, 500)
    lon = rng.uniform(-180, 180, 500)
    p = make_partition("kmeans", lat, lon, clusters=12)
    assert len(p.names) == 12 and p.params["effective_clusters"] == 12
    # independent check: each point's cluster has the nearest centroid on the sphere (chord
    # distance in 3D is monotonic in great-circle distance)
    xyz = latlon_to_unit(lat, lon)
    cen = latlon_to_unit(p.centroids[:, 0], p.centroids[:, 1])
    nearest = np.argmax(xyz @ cen.T, axis=1)
    assert np.mean(nearest == p.labels) > 0.99
    for i in range(12):
        d = haversine_km(lat[i], lon[i], p.centroids[:, 0], p.centroids[:, 1])
        assert nearest_centroids(lat[i], lon[i], p.centroids, 1)[0] == int(np.argmin(d))


def test_kmeans_clamps_k_and_spans_antimeridian():
    lat = [10.0, 10.1, 10.0, -40.0]
    lon = [179.9, -179.9, 179.95, 20.0]
    p = make_partition("kmeans", lat, lon, clusters=100)
    assert len(p.names) <= 4
    p2 = make_partition("kmeans", lat, lon, clusters=2)
    assert p2.labels[0] == p2.labels[1] == p2.labels[2] != p2.labels[3]


def test_unknown_partition_lists_choices():
    with pytest.raises(ConfigError, match="country, kmeans, none"):
        make_partition("voronoi", [0.0], [0.0])
