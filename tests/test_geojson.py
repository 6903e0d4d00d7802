"""Results as GeoJSON (RFC 7946): `vlm-vpr evaluate --geojson`. Checked against the CSV it was
written from and an independent great-circle distance (spherical law of cosines)."""

from __future__ import annotations

import csv
import json
import math

import pytest

from vlm_vpr_ros.cli import main
from vlm_vpr_ros.files.geojson import result_feature, results_collection

ROWS = [
    {"file": "a.jpg", "lat": "48.8584", "lon": "2.2945", "ref_id": "fr/1.jpg", "status": "fix",
     "flags": "", "uncertainty_m": "25.0", "radius95_m": "40", "p_correct": "0.97",
     "confidence": "0.9"},
    {"file": "b.jpg", "lat": "-33.8568", "lon": "151.2153", "ref_id": "au/2.jpg",
     "status": "no_fix", "flags": "prior_far_from_match|no_rerank", "uncertainty_m": "",
     "radius95_m": "nan", "p_correct": "", "confidence": "0.2"},
    {"file": "c.jpg", "lat": "nan", "lon": "nan", "ref_id": "", "status": "no_fix",
     "flags": "no_match", "uncertainty_m": "", "radius95_m": "", "p_correct": "",
     "confidence": "0"},
]
TRUTH = {"a.jpg": (48.8606, 2.3376), "b.jpg": (-33.8568, 151.2153), "c.jpg": (0.0, 0.0)}


def _km(lat1, lon1, lat2, lon2, r=6371.0088):
    p1, p2, dl = math.radians(lat1), math.radians(lat2), math.radians(lon2 - lon1)
    c = math.sin(p1) * math.sin(p2) + math.cos(p1) * math.cos(p2) * math.cos(dl)
    return r * math.acos(max(-1.0, min(1.0, c)))


@pytest.fixture
def files(tmp_path):
    res, gt = tmp_path / "results.csv", tmp_path / "gt.csv"
    with res.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(ROWS[0]))
        w.writeheader()
        w.writerows(ROWS)
    with gt.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["file", "lat", "lon"])
        w.writerows([k, *v] for k, v in TRUTH.items())
    return res, gt


def test_evaluate_writes_rfc7946_lon_lat(files, tmp_path, capsys):
    res, gt = files
    out = tmp_path / "results.geojson"
    assert main(["evaluate", "--results", str(res), "--ground-truth", str(gt),
                 "--geojson", str(out)]) == 0
    assert "(2 points)" in capsys.readouterr().err
    doc = json.loads(out.read_text())
    assert doc["type"] == "FeatureCollection" and "crs" not in doc
    feats = doc["features"]
    assert [f["properties"]["file"] for f in feats] == ["a.jpg", "b.jpg", "c.jpg"]
    for f, row in zip(feats[:2], ROWS):
        assert f["type"] == "Feature" and f["geometry"]["type"] == "Point"
        lon, lat = f["geometry"]["coordinates"]  # RFC 7946: longitude first
        assert (lat, lon) == (float(row["lat"]), float(row["lon"]))
        assert -180 <= lon <= 180 and -90 <= lat <= 90
    a, b, c = (f["properties"] for f in feats)
    assert a["truth"] == [2.3376, 48.8606]
    assert a["error_km"] == pytest.approx(_km(48.8584, 2.2945, 48.8606, 2.3376), abs=1e-4)
    assert b["error_km"] == 0.0
    assert a["status"] == "fix" and a["p_correct"] == 0.97 and a["uncertainty_m"] == 25.0
    assert b["flags"] == ["prior_far_from_match", "no_rerank"]
    assert b["uncertainty_m"] is None and b["radius95_m"] is None  # empty, nan: null not NaN
    # no estimate: kept, without geometry (RFC 7946 3.2), its flags say why
    assert feats[2]["geometry"] is None and c["flags"] == ["no_match"] and c["error_km"] is None
    assert "NaN" not in out.read_text()


def test_without_truth_and_bad_positions():
    doc = results_collection([{"file": "x", "lat": "91", "lon": "0"},
                              {"file": "y", "lat": "10", "lon": "-190"},
                              {"file": "z", "lat": "1e1", "lon": "20.123456789"}])
    geoms = [f["geometry"] for f in doc["features"]]
    assert geoms[:2] == [None, None]
    assert geoms[2] == {"type": "Point", "coordinates": [20.1234568, 10.0]}
    assert "truth" not in doc["features"][2]["properties"]
    assert result_feature({"file": "w", "lat": "", "lon": ""}, (1.0, 2.0))["properties"][
        "truth"] == [2.0, 1.0]


def test_missing_results_file_is_one_line_error(tmp_path, caplog):
    gt = tmp_path / "gt.csv"
    gt.write_text("file,lat,lon\na,1,2\n")
    rc = main(["evaluate", "--results", str(tmp_path / "none.csv"), "--ground-truth", str(gt),
               "--geojson", str(tmp_path / "o.geojson")])
    assert rc == 2 and "none.csv" in caplog.text
    assert not (tmp_path / "o.geojson").exists()
