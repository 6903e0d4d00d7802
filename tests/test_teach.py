"""Teach run: bag → references (interpolation, fix filtering, spacing), ``build-map --bag`` and
its bad-input errors. Generated bags use the project's writer with real ROS 2 serialization;
the checks on the real shared bags and on sf_night skip when ../shared is absent."""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from teach_bags import Place, drive_order, mcap_to_db3, write_teach_bag
from vlm_vpr_ros.bags.teach import (TeachConfig, _Fixes, distance_m, extract_references,
                                    interpolate_fix)
from vlm_vpr_ros.cli import main
from vlm_vpr_ros.errors import BagError, ConfigError
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.mapping.coords_csv import read_coords_csv
from vlm_vpr_ros.maps.map_images import verify_images
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

S = 1_000_000_000


def cli(caplog, *args) -> tuple[int, str]:
    """Run ``vlm-vpr ARGS`` in-process: (exit code, the error lines it logged)."""
    caplog.clear()
    with caplog.at_level(logging.ERROR):
        rc = main([str(a) for a in args])
    return rc, "\n".join(r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR)


# -- pure pairing rules ----------------------------------------------------------------------
def _straight_drive(speed_mps=12.0, hz=10.0, n=200, lat0=37.77, lon0=-122.42):
    """Fixes of a robot driving due east at constant speed (known position at any time)."""
    m_per_deg = 111_194.9 * math.cos(math.radians(lat0))
    stamps = [int(k * S / hz) for k in range(n)]
    pos = lambda t: (lat0, lon0 + speed_mps * t / 1e9 / m_per_deg)  # noqa: E731
    return _Fixes(stamps, [pos(t)[0] for t in stamps], [pos(t)[1] for t in stamps]), pos


def test_interpolation_matches_known_motion():
    fixes, pos = _straight_drive()
    rng = np.random.default_rng(0)
    for t in rng.integers(0, fixes.stamps[-1], 300):
        got = interpolate_fix(fixes, int(t), S // 2)
        assert distance_m(*got, *pos(int(t))) < 0.01  # 12 m/s between 10 Hz fixes
    # exactly on a fix (and within 1 ms of it): that fix
    assert interpolate_fix(fixes, fixes.stamps[7] + 500_000, S // 2) == (fixes.lat[7],
                                                                          fixes.lon[7])
    # before the first / after the last fix: nothing to interpolate between
    assert interpolate_fix(fixes, -S, S // 2) is None
    assert interpolate_fix(fixes, fixes.stamps[-1] + S // 10, S // 2) is None


def test_interpolation_needs_a_fix_on_both_sides_within_tolerance():
    f = _Fixes([0, 2 * S], [10.0, 10.0], [20.0, 20.002])
    assert interpolate_fix(f, S, S // 2) is None  # 1 s from both: gap
    assert interpolate_fix(f, S, S) == pytest.approx((10.0, 20.001))
    wrap = _Fixes([0, S], [0.0, 0.0], [179.9999, -179.9999])  # across the antimeridian
    lat, lon = interpolate_fix(wrap, S // 2, S)
    assert abs(lon) == pytest.approx(180.0) and lat == 0.0


def test_config_is_checked():
    with pytest.raises(ConfigError, match="fix-tolerance"):
        TeachConfig(fix_tolerance_s=0)
    with pytest.raises(ConfigError, match="min-spacing"):
        TeachConfig(min_spacing_m=-1)


# -- generated teach bags (no ../shared needed) ------------------------------------------------
@pytest.fixture(scope="module")
def demo_places(demo_data):
    rows = read_coords_csv(demo_data / "coords.csv")[:16]
    return [Place(load_image(demo_data / "images" / f)[::2, ::2].copy(), la, lo)
            for f, la, lo in rows]


@pytest.fixture(scope="module")
def raw_bag(demo_places, tmp_path_factory):
    out = tmp_path_factory.mktemp("teach") / "drive_raw"
    return write_teach_bag(out, demo_places, gaps=(3, 9), standstill=6)


def test_extraction_counts_every_reason(raw_bag, tmp_path):
    res = extract_references(raw_bag.path, tmp_path / "img", progress=False)
    inj = raw_bag.injected
    assert res.frames["kept"] == len(raw_bag.truth) == 16
    assert res.frames["closer_than_min_spacing"] == inj["standstill_frames"]
    assert res.frames["no_fix_within_tolerance"] == inj["gap_frames"]
    for reason in ("no_fix_status", "invalid_position", "sigma_above_max", "used"):
        assert res.fixes[reason] == inj[reason] > 0, reason
    for r in res.references:
        assert distance_m(r.lat, r.lon, *raw_bag.truth[r.stamp_ns]) < 1.0
        assert r.id == f"drive_raw/{r.stamp_ns // S}.{r.stamp_ns % S:09d}.jpg"
        assert (tmp_path / "img" / r.id).read_bytes()[:3] == b"\xff\xd8\xff"
    assert "16 references kept" in res.describe() and "no_fix_status" in res.describe()


def test_build_map_from_bag_cli(raw_bag, demo_places, tmp_path, capsys, monkeypatch):
    out = tmp_path / "teach_map"
    rc = main(["build-map", "--bag", str(raw_bag.path), "--out", str(out), "--descriptor",
               "vlad_rootsift_fast", "--descriptor-option", "max_side=320", "--clusters", "4"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "16 references kept" in text and "images stored in the map" in text
    m = ReferenceMap.load(out)
    assert m.n_references == 16 and verify_images(out) == 16
    manifest = json.loads((out / "manifest.json").read_text())
    teach = manifest["source"]["teach"]
    assert teach["frames"]["kept"] == 16 and teach["fix_topic"] == "/gps/fix"
    # every place is localized to itself from the stored JPEG (the map is self-contained)
    pipe = LocalizationPipeline.open(out)
    for ref_id, (lat, lon) in zip(m.all_ids(), m.all_coords()):
        hyp = pipe.localize_image(load_image(out / "images" / ref_id))
        assert hyp.ref_id == ref_id
    # the output is never overwritten without --overwrite
    assert main(["build-map", "--bag", str(raw_bag.path), "--out", str(out)]) == 2
    assert ReferenceMap.load(out).n_references == 16
    assert not list(tmp_path.glob(".teach_map*"))  # no staging left behind
    # --overwrite cut short between the two renames of the swap (Ctrl-C): the old map is put
    # back (before: it was left as .teach_map.old<pid> and out/ was missing)
    before = (out / "manifest.json").read_bytes()
    real = os.replace

    def interrupted(src, dst):
        real(src, dst)
        if Path(src) == out:
            raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    assert main(["build-map", "--bag", str(raw_bag.path), "--out", str(out), "--overwrite",
                 "--descriptor", "vlad_rootsift_fast", "--descriptor-option", "max_side=320",
                 "--clusters", "4"]) == 130
    monkeypatch.setattr(os, "replace", real)
    assert (out / "manifest.json").read_bytes() == before and verify_images(out) == 16
    assert sorted(p.name for p in tmp_path.iterdir()) == ["teach_map"]
    # map upgrade to another index keeps the stored images (and their index) and features
    up = tmp_path / "teach_fp16"
    assert main(["map", "upgrade", str(out), "--out", str(up), "--index", "fp16"]) == 0
    assert verify_images(up) == 16
    ref_id = m.all_ids()[3]
    hyp = LocalizationPipeline.open(up).localize_image(load_image(up / "images" / ref_id))
    assert hyp.ref_id == ref_id and hyp.verification == "verified"


def test_sqlite3_teach_bag(raw_bag, tmp_path):
    db3 = mcap_to_db3(raw_bag.path, tmp_path / "drive.db3")
    res = extract_references(db3, tmp_path / "img", progress=False)
    assert res.frames["kept"] == 16 and res.references[0].id.startswith("drive/")
    for r in res.references:
        assert distance_m(r.lat, r.lon, *raw_bag.truth[r.stamp_ns]) < 1.0


def test_topic_choice_errors(demo_places, tmp_path, caplog):
    two = write_teach_bag(tmp_path / "two_cams", demo_places[:3],
                          extra_image_topic="/camera2/image_raw").path
    with pytest.raises(BagError, match="several topics.*/camera/image_raw, /camera2/image_raw"):
        extract_references(two, tmp_path / "a", progress=False)
    res = extract_references(two, tmp_path / "b", TeachConfig(image_topic="/camera2/image_raw"),
                             progress=False)
    assert res.image_topic == "/camera2/image_raw" and res.frames["kept"] == 3
    rc, err = cli(caplog, "build-map", "--bag", two, "--out", tmp_path / "m", "--image-topic",
                  "/camera/image_raw", "--fix-topic", "/nope")
    assert rc == 2 and "no topic '/nope'" in err and "/camera2/image_raw [" in err


def test_fixes_and_frames_never_overlap(demo_places, tmp_path, caplog):
    bag = write_teach_bag(tmp_path / "late_gps", demo_places[:3], fix_offset_s=3600.0).path
    rc, err = cli(caplog, "build-map", "--bag", bag, "--out", tmp_path / "m")
    assert rc == 2 and "never overlap in time" in err and "/gps/fix" in err
    assert not (tmp_path / "m").exists()


def test_images_and_bag_are_exclusive(raw_bag, tmp_path, caplog):
    rc, err = cli(caplog, "build-map", "--bag", raw_bag.path, "--images", tmp_path, "--coords",
                  "x.csv", "--out", tmp_path / "m")
    assert rc == 2 and "not both" in err
    rc, err = cli(caplog, "build-map", "--out", tmp_path / "m")
    assert rc == 2 and "--bag BAG" in err


# -- the real bags of ../shared -----------------------------------------------------------------
@pytest.mark.parametrize("name, expect", [
    ("stinger_localization_bag_sqlite3", ("/gps/fix", "/imu/data", "/tf")),
    ("event_camera_py_test_events_2", ("event_camera_msgs/msg/EventPacket",)),
])
def test_real_bags_without_camera_frames(shared_dir, tmp_path, name, expect):
    proc = subprocess.run([sys.executable, "-m", "vlm_vpr_ros.cli", "build-map", "--bag",
                           str(shared_dir / "data" / "bags" / name), "--out",
                           str(tmp_path / "m")], capture_output=True, text=True, timeout=120)
    err = proc.stderr
    assert proc.returncode == 2 and len(err.strip().splitlines()) == 1, err
    assert "camera images" in err and "the bag has:" in err
    for topic in expect:
        assert topic in err
    assert not (tmp_path / "m").exists()


# -- sf_night: a real retrieval task --------------------------------------------------------
#: quick settings, the same for both maps (docs/teach.md has the full-size figures)
FAST = ["--descriptor", "vlad_rootsift_fast", "--descriptor-option", "max_side=320",
        "--clusters", "6"]


def _recall_at_1(map_dir, root, queries):
    pipe = LocalizationPipeline.open(map_dir)
    hits = 0
    for f, lat, lon in queries:
        hyp = pipe.localize_image(load_image(root / f))
        hits += haversine_km(lat, lon, hyp.lat, hyp.lon) * 1000 <= 25
    return hits


def test_sf_night_teach_bag_matches_folder_map(shared_dir, tmp_path, caplog):
    """A drive past the sf_night database places (every place with a match for a query within
    25 m, and every 6th other place, ~110: a third of the database keeps the test quick) →
    build-map --bag; the folder map of the same places is the baseline."""
    root = shared_dir / "data" / "sf_night"
    rows = read_coords_csv(root / "database.csv")
    queries = read_coords_csv(root / "queries.csv")
    la, lo = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    near = set()
    for _, a, b in queries:
        near |= set(np.flatnonzero(haversine_km(a, b, la, lo) * 1000 <= 25).tolist())
    dates = {r["file"]: r["date"] for r in csv.DictReader(open(root / "database.csv"))}
    rows = [r for i, r in enumerate(rows) if i in near or i % 6 == 0]
    rows = drive_order(sorted(rows, key=lambda r: dates[r[0]]))  # drives date by date
    places = [Place((root / f).read_bytes(), a, b) for f, a, b in rows]
    bag = write_teach_bag(tmp_path / "sf_drive", places, gaps=(10, 40, 80), standstill=50)
    rc, err = cli(caplog, "build-map", "--bag", bag.path, "--out", tmp_path / "teach", *FAST)
    assert rc == 0, err
    teach = ReferenceMap.load(tmp_path / "teach")
    stamps = {r: int(r.split("/")[1].split(".")[0]) * S + int(r.split(".")[1])
              for r in teach.all_ids()}
    err_m = [distance_m(la, lo, *bag.truth[stamps[r]])
             for r, (la, lo) in zip(teach.all_ids(), teach.all_coords())]
    assert max(err_m) < 1.0
    # the spacing rule, independently: places closer than 2 m to the last kept one are dropped
    kept, last = 0, None
    for _, a, b in rows:
        if last is None or distance_m(*last, a, b) >= 2.0:
            kept, last = kept + 1, (a, b)
    assert teach.n_references == kept
    places_csv = tmp_path / "places.csv"
    places_csv.write_text("file,lat,lon\n" + "".join(f"{f},{a!r},{b!r}\n" for f, a, b in rows))
    rc, err = cli(caplog, "build-map", "--images", root, "--coords", places_csv, "--out",
                  tmp_path / "folder", *FAST)
    assert rc == 0, err
    r_teach = _recall_at_1(tmp_path / "teach", root, queries)
    r_folder = _recall_at_1(tmp_path / "folder", root, queries)
    print(f"sf_night R@1 (25 m): teach-bag map {r_teach}/34, folder map {r_folder}/34")
    assert r_folder >= 8  # a broken descriptor gives ~0 (chance is < 2 %)
    assert abs(r_teach - r_folder) <= 1
