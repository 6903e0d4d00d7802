"""Round 4 (issue 28), stored files: the local-feature store checked against the manifest like
every other map file; writer locks that never follow a symbolic link; output paths checked
before any work."""

from __future__ import annotations

import csv
import json
import os

import numpy as np
import pytest

from faults.conftest import exit2, sha_tree


def _lf(man: dict, k: int, role: str) -> str:
    return man["local_features"]["submaps"][man["submaps"][k]["id"]]["files"][role]


def _open(m):
    from vlm_vpr_ros.maps.features import FeatureStore

    return FeatureStore.open(m, json.loads((m / "manifest.json").read_text()))


@pytest.mark.fault("features_not_the_manifest")
def test_feature_files_checked_against_manifest(cli, map_copy, demo_data, queries, tmp_path,
                                                caplog):
    from vlm_vpr_ros.errors import MapError

    m = map_copy
    man = json.loads((m / "manifest.json").read_text())
    assert _open(m) is not None
    pristine = {p: p.read_bytes() for p in (m / "submaps").glob("*.lf_*.npy")}
    # 1. each role of submap 0 given another submap's bytes, same size (a swap sizes miss)
    for role in ("rows", "keypoints", "descriptors"):
        a, b = m / _lf(man, 0, role), m / _lf(man, 1, role)
        raw, other = a.read_bytes(), b.read_bytes()
        a.write_bytes((other * (len(raw) // len(other) + 1))[:len(raw)])
        assert a.stat().st_size == len(raw)
        with pytest.raises(MapError, match="does not match the manifest") as ei:
            _open(m)
        assert _lf(man, 0, role) in str(ei.value)
        a.write_bytes(raw)
    # 2. garbage bytes in a small lf_kpts (the .npy header kept)
    kp = m / _lf(man, 2, "keypoints")
    raw = kp.read_bytes()
    assert len(raw) <= 256 * 1024
    kp.write_bytes(raw[:128] + np.random.default_rng(0).bytes(len(raw) - 128))
    with pytest.raises(MapError, match="does not match the manifest"):
        _open(m)
    kp.write_bytes(raw)
    # 3. a wrong sha256 for lf_desc in the manifest (the file itself untouched)
    bad = json.loads((m / "manifest.json").read_text())
    rel = _lf(man, 3, "descriptors")
    bad["files"][rel]["sha256"] = "0" * 64
    bad["files"][rel].pop("sample", None)
    if bad["files"][rel]["bytes"] > 256 * 1024:  # large: the sampled-page fingerprint instead
        bad["files"][rel]["sample"] = "0" * 64
    (m / "manifest.json").write_text(json.dumps(bad))
    with pytest.raises(MapError, match="does not match the manifest"):
        _open(m)
    (m / "manifest.json").write_text(json.dumps(man))
    # 4. the CLI on a swapped store: never a verified answer from the wrong features
    a = m / _lf(man, 0, "descriptors")
    raw = a.read_bytes()
    a.write_bytes(raw[:128] + bytes(len(raw) - 128))
    out = tmp_path / "r.csv"
    rc, _, _ = cli("localize", "--map", m, "--images", demo_data / "images", "--queries",
                   queries, "--out", out, "--prior", "none")
    assert rc == 0
    assert _lf(man, 0, "descriptors") in cli.text and "does not match the manifest" in cli.text
    rows = list(csv.DictReader(out.open()))
    assert rows and all("unverified" in r["flags"].split("|") and r["status"] == "no_fix"
                        for r in rows), [(r["flags"], r["status"]) for r in rows]
    a.write_bytes(raw)
    assert {p: p.read_bytes() for p in pristine} == pristine
    assert _open(m) is not None


@pytest.mark.fault("features_rewritten_while_open")
def test_feature_file_rewritten_after_open(map_copy):
    from vlm_vpr_ros.errors import MapError

    m = map_copy
    man = json.loads((m / "manifest.json").read_text())
    store = _open(m)
    sid = man["submaps"][0]["id"]
    assert len(store.get(sid, 0)) >= 0
    p = m / _lf(man, 0, "keypoints")
    raw = p.read_bytes()
    with open(p, "r+b") as fh:  # in place, same size, same inode
        fh.seek(128)
        fh.write(bytes(len(raw) - 128))
    os.utime(p, ns=(p.stat().st_atime_ns, p.stat().st_mtime_ns + 10**9))
    with pytest.raises(MapError, match="does not match the manifest"):
        store.get(sid, 0)
    p.write_bytes(raw)
    with pytest.raises(MapError):  # refused until reloaded
        store.get(sid, 0)
    assert _open(m).get(sid, 0) is not None


@pytest.mark.fault("features_bad_caps")
def test_feature_caps_and_missing_section(map_copy):
    from vlm_vpr_ros.errors import MapError

    m = map_copy
    man = json.loads((m / "manifest.json").read_text())
    for key, v in (("max_keypoints", -1), ("query_max_keypoints", "x")):
        bad = json.loads(json.dumps(man))
        bad["local_features"][key] = v
        (m / "manifest.json").write_text(json.dumps(bad))
        with pytest.raises(MapError) as ei:
            _open(m)
        assert f"local_features.{key}" in str(ei.value) and str(m) in str(ei.value)
    bad = json.loads(json.dumps(man))
    bad["local_features"]["submaps"].pop(man["submaps"][0]["id"])
    (m / "manifest.json").write_text(json.dumps(bad))
    with pytest.raises(MapError) as ei:
        _open(m)
    assert "map features" not in str(ei.value) and "vlm-vpr build-map" in str(ei.value)


# -- the writer lock never follows a symbolic link ---------------------------------------------
@pytest.mark.fault("lock_symlink_file")
def test_lock_file_symlink_never_followed(cli, map_copy, tmp_path, monkeypatch):
    """`PARENT/.MAP.lock` or `MAP/.edit.lock` a symbolic link to a user's file, or dangling:
    refused naming the link; the user's file untouched, nothing created at the target."""
    from vlm_vpr_ros.files.lock import WriterLock

    monkeypatch.setenv("VLM_VPR_LOCK_WAIT_S", "0")
    ids = tmp_path / "ids.txt"
    ids.write_text("x\n")
    user = tmp_path / "user_notes.txt"
    user.write_text("my precious notes\n")
    before = sha_tree(map_copy)
    for link in (tmp_path / ".map.lock", map_copy / ".edit.lock"):
        for target in (user, tmp_path / "elsewhere" / "created.txt", tmp_path / "new.txt"):
            (tmp_path / "elsewhere").mkdir(exist_ok=True)
            link.symlink_to(target)
            err = exit2(cli("map", "remove", map_copy, "--ids", ids), str(link),
                        "symbolic link")
            assert "Traceback" not in err
            assert user.read_text() == "my precious notes\n"
            assert not (tmp_path / "elsewhere" / "created.txt").exists()
            assert not (tmp_path / "new.txt").exists()
            assert link.is_symlink()  # the user's link is left for the user to remove
            with pytest.raises(OSError, match="symbolic link"):
                WriterLock(map_copy, "test", inside_ok=True).acquire()
            link.unlink()
    assert sha_tree(map_copy) == before
    # a holder whose lock name was replaced by a link neither deletes nor writes through it
    lock = WriterLock(map_copy, "test").acquire()
    lp = tmp_path / ".map.lock"
    lp.unlink()
    lp.symlink_to(user)
    assert lock.holder() == ""  # the holder line is never read through a link
    lock.release()
    assert lp.is_symlink() and user.read_text() == "my precious notes\n"
    lp.unlink()
    # the plain case still works: the lock file is made, then removed
    rc, _, _ = cli("map", "remove", map_copy, "--ids", ids)
    assert not lp.exists() and not (map_copy / ".edit.lock").exists()


# -- --save-matches: checked before any work ----------------------------------------------------
@pytest.mark.fault("out_save_matches")
def test_save_matches_checked_before_any_work(cli, map_copy, demo_data, queries, tmp_path):
    """`--save-matches X`: X an existing file, X a folder holding same-named pictures, X inside
    the map: exit 2 before any query, nothing written; --overwrite replaces only the pictures."""
    from vlm_vpr_ros.evaluation.matches import sheet_names

    files = queries.read_text().split()[1:]
    base = ["localize", "--map", map_copy, "--images", demo_data / "images", "--queries",
            queries, "--prior", "none"]
    mine = tmp_path / "notes.txt"
    mine.write_text("mine\n")
    out = tmp_path / "r.csv"
    exit2(cli(*base, "--out", out, "--save-matches", mine), str(mine), "not a folder")
    assert mine.read_text() == "mine\n" and not out.exists()
    assert not out.with_name("r.csv.partial").exists()
    folder = tmp_path / "pics"
    folder.mkdir()
    name = sheet_names(files)[files[0]]
    (folder / name).write_bytes(b"my own picture")
    (folder / "keep.txt").write_text("keep")
    before = sha_tree(folder)
    exit2(cli(*base, "--out", out, "--save-matches", folder), str(folder), name, "--overwrite")
    assert sha_tree(folder) == before and not out.exists()
    exit2(cli(*base, "--out", out, "--save-matches", map_copy / "pics"), "--save-matches",
          "inside")
    assert not (map_copy / "pics").exists()
    # two queries whose names differ only in unsafe characters get two pictures
    names = sheet_names(["a b.jpg", "a_b.jpg", "a b.jpg"])
    assert len(set(names.values())) == 2 and names["a b.jpg"] != names["a_b.jpg"]


# -- metric frames: a far fix gets no pose ----------------------------------------------------
@pytest.mark.fault("pose_fixed_zone_far")
def test_fixed_zone_or_datum_far_from_the_fix_gives_no_pose():
    """A fixed `utm_zone` with fixes 85-180 deg of longitude away, a local_enu datum 7,000 km
    away: refused with the reason (no pose), never finite nonsense; near fixes still served."""
    from pyproj import Transformer

    from vlm_vpr_ros.errors import ConfigError
    from vlm_vpr_ros.runtime.metric_frame import MetricFrame

    f = MetricFrame("utm", zone=31)  # central meridian 3 E
    for lon in (88.0, 120.0, 183.0 - 360.0, -177.0, 180.0):
        with pytest.raises(ConfigError, match="fixed UTM zone 31"):
            f.pose(10.0, lon, 0.0, (1.0, 0, 0, 0, 1.0, 0, 0, 0, 4.0))
    # neighbours of the zone: served, and equal to PROJ's own transverse Mercator
    ref = Transformer.from_crs("EPSG:4326", "EPSG:32631", always_xy=True)
    for lon in (-2.9, 8.9, 14.5):
        x, y, _ = f.project(48.0, lon, 0.0)
        assert (x, y) == pytest.approx(ref.transform(lon, 48.0), abs=1e-6)
    enu = MetricFrame("local_enu", datum=(-31.95, 115.86))  # Perth
    with pytest.raises(ConfigError, match="km from the local_enu datum"):
        enu.project(9.93, 76.26, 0.0)  # Kochi, Kerala: ~7,000 km
    x, y, _ = enu.project(-31.95 + 0.01, 115.86, 0.0)
    assert abs(x) < 1.0 and 1100 < y < 1120


@pytest.mark.fault("writers_symlink_names")
def test_writers_replace_links_never_follow_them(tmp_path):
    """A symbolic link to a user's file left at an output marker's name or at a writer's
    temporary name (feature files: `.NAME.tmpPID`): the user's file untouched, the output a
    regular file."""
    from vlm_vpr_ros.files.outputs import MARKER, write_marker
    from vlm_vpr_ros.maps.features import feature_files, write_submap_features
    from vlm_vpr_ros.types import LocalFeatures

    user = tmp_path / "user.txt"
    user.write_text("precious\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / MARKER).symlink_to(user)
    write_marker(out, "bag")
    assert user.read_text() == "precious\n"
    assert not (out / MARKER).is_symlink() and json.loads((out / MARKER).read_text())["kind"]
    root = tmp_path / "map"
    (root / "submaps").mkdir(parents=True)
    rels = feature_files("k000")
    for rel in rels.values():
        p = root / rel
        p.with_name(f".{p.name}.tmp{os.getpid()}").symlink_to(user)
    feats = [LocalFeatures(np.ones((3, 2), np.float32), np.ones((3, 128), np.uint8), (64, 48))]
    write_submap_features(root, "k000", feats, np.dtype(np.uint8), 128)
    assert user.read_text() == "precious\n"
    for rel in rels.values():
        assert (root / rel).is_file() and not (root / rel).is_symlink()
    assert np.load(root / rels["keypoints"]).shape == (3, 2)


@pytest.mark.fault("out_details_csv")
def test_priors_score_details_checked_before_any_work(cli, tmp_path):
    """`priors score --details X`: X a user's file, a folder, or the answers / ground truth
    themselves: exit 2 before any work, untouched; a details CSV written before is replaced."""
    (tmp_path / "a.csv").write_text('filename,response\na.jpg,"48.85, 2.35"\n')
    (tmp_path / "gt.csv").write_text("file,lat,lon\na.jpg,48.85,2.35\n")
    mine = tmp_path / "notes.csv"
    mine.write_text("my,own\n1,2\n")
    base = ["priors", "score", "--answers", tmp_path / "a.csv", "--ground-truth",
            tmp_path / "gt.csv", "--details"]
    before = sha_tree(tmp_path)
    exit2(cli(*base, mine), str(mine), "left untouched")
    exit2(cli(*base, tmp_path), "is a folder")
    exit2(cli(*base, tmp_path / "gt.csv"), "is the input")
    exit2(cli(*base, tmp_path / "a.csv"), "is the input")
    assert sha_tree(tmp_path) == before
    out = tmp_path / "d.csv"
    assert cli(*base, out)[0] == 0 and cli(*base, out)[0] == 0  # ours: replaced
    assert list(csv.DictReader(out.open()))[0]["file"] == "a.jpg"


# -- round 5 (issue 43) --------------------------------------------------------------------------
_RESULTS = ("file,lat,lon,ref_id,status,flags,uncertainty_m,radius95_m,p_correct\n"
            "a.jpg,48.8584,2.2945,r1,fix,,25,60,0.97\n")


@pytest.mark.fault("out_geojson_over_inputs")
def test_geojson_never_over_an_input_or_a_users_file(cli, tmp_path):
    """Before: exit 0, the results CSV (or the ground truth, or notes.txt) replaced by
    GeoJSON."""
    res, gt, notes = tmp_path / "r.csv", tmp_path / "gt.csv", tmp_path / "notes.txt"
    res.write_text(_RESULTS)
    gt.write_text("file,lat,lon\na.jpg,48.8606,2.3376\n")
    notes.write_text("my notes\n")
    os.symlink(gt, tmp_path / "gt_link.csv")
    before = sha_tree(res, gt, notes)
    for target in (res, gt, tmp_path / "gt_link.csv", notes):
        exit2(cli("evaluate", "--results", res, "--ground-truth", gt, "--geojson", target,
                  "--overwrite"), str(target))
        assert sha_tree(res, gt, notes) == before and not (tmp_path / "r_integrity").exists()
    ours = tmp_path / "r.geojson"
    for _ in range(2):  # a GeoJSON of ours is replaced
        assert cli("evaluate", "--results", res, "--ground-truth", gt, "--geojson", ours,
                   "--overwrite")[0] == 0
        assert json.loads(ours.read_text())["type"] == "FeatureCollection"
    assert sha_tree(res, gt, notes) == before


@pytest.mark.fault("out_ablate_over_inputs")
def test_ablate_out_never_over_inputs(cli, map_copy, demo_data, tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "ablation.json").write_text('{"my": "numbers"}\n')
    q = tmp_path / "q.csv"
    q.write_text("file,lat,lon\n" + "".join(
        ",".join(r) + "\n" for r in list(csv.reader(open(demo_data / "coords.csv")))[1:4]))
    before = sha_tree(map_copy, mine)
    for out, needle in ((map_copy, "is the input"), (map_copy / "ablation", "inside"),
                        (mine, "not an ablation.json this command wrote")):
        exit2(cli("ablate", "--map", map_copy, "--images", demo_data / "images", "--queries",
                  q, "--out", out, "--top-p", "1"), needle)
        assert sha_tree(map_copy, mine) == before


# -- round 5 (issue 43): found elsewhere ----------------------------------------------------------
@pytest.mark.fault("localize_checks_before_map")
def test_localize_checks_everything_before_the_map(cli, demo_map, demo_data, queries, tmp_path,
                                                   map_loads):
    """Before: the map (and the descriptor model) loaded first, then exit 2 on the prior."""
    name = queries.read_text().split()[1]
    bad = tmp_path / "p.csv"
    bad.write_text(f"file,lat,lon,sigma_m\n{name},37.7,-122.4,3e7\n")
    out = tmp_path / "r.csv"
    base = ["localize", "--map", demo_map, "--images", demo_data / "images", "--queries",
            queries, "--out", out]
    for extra, needle in ((("--priors", bad), "sigma_m"),
                          (("--prior", "fixed", "--prior-option", "lat=1", "--prior-option",
                            "lon=2", "--prior-option", "sigma_km=1e-300"), "sigma_km"),
                          (("--fix-min-p-correct", "0"), "fix_min_p_correct"),
                          (("--only-wrong",), "--only-wrong")):
        exit2(cli(*base, *extra), needle)
        assert not map_loads and not out.exists()


@pytest.mark.fault("bag_checks_priors_before_map")
def test_bag_commands_check_the_priors_before_the_map(cli, demo_map, demo_data, queries,
                                                      tmp_path, map_loads):
    """Before: `evaluate-bag` and `ablate` opened the map first, then exit 2 on the priors."""
    from vlm_vpr_ros.bags.make import make_bag

    bag = tmp_path / "bag"
    coords = tmp_path / "coords.csv"
    coords.write_text("\n".join((demo_data / "coords.csv").read_text().splitlines()[:3]) + "\n")
    make_bag(demo_data / "images", coords, bag, progress=False)
    bad = tmp_path / "p.csv"
    bad.write_text(f"file,lat,lon,sigma_m\n{queries.read_text().split()[1]},37.7,-122.4,3e7\n")
    for cmd in (["evaluate-bag", bag], ["ablate", "--bag", bag]):
        out = tmp_path / f"out_{cmd[0]}"
        exit2(cli(*cmd, "--map", demo_map, "--priors", bad, "--out", out), str(bad), "sigma_m")
        assert not map_loads and not out.exists()


@pytest.mark.fault("out_localize_over_inputs")
def test_localize_out_never_an_input(cli, demo_map, demo_data, queries, tmp_path, map_loads):
    """Before: `--queries r.csv --out r.csv --overwrite` replaced the queries (a results CSV of
    ours) with the results; the priors CSV and the ground truth alike."""
    r = tmp_path / "r.csv"
    base = ["localize", "--map", demo_map, "--images", demo_data / "images"]
    assert cli(*base, "--queries", queries, "--out", r)[0] == 0
    map_loads.clear()
    pri = tmp_path / "pri.csv"
    os.link(r, pri)
    before = sha_tree(tmp_path)
    for mode in ("--overwrite", "--resume"):
        exit2(cli(*base, "--queries", r, "--out", r, mode), "is the input")
        exit2(cli(*base, "--queries", queries, "--priors", r, "--out", pri, mode),
              "is the input")
        exit2(cli(*base, "--queries", queries, "--out", r, "--save-matches", tmp_path / "m",
                  "--ground-truth", r, mode), "is the input")
        assert sha_tree(tmp_path) == before and not map_loads


@pytest.mark.fault("out_save_matches_inputs")
def test_save_matches_never_over_inputs_or_a_users_files(cli, demo_map, demo_data, queries,
                                                         tmp_path, map_loads):
    """Before: `--save-matches IMAGES --overwrite` replaced a user's file of a picture's name
    inside the query images."""
    import shutil

    from vlm_vpr_ros.evaluation.matches import sheet_names

    files = queries.read_text().split()[1:]
    name = sheet_names(files)[files[0]]
    imgs, mine = tmp_path / "imgs", tmp_path / "mine"
    shutil.copytree(demo_data / "images", imgs)
    mine.mkdir()
    for d in (imgs, mine):
        (d / name).write_bytes(b"a picture of mine")
    (mine / "notes.txt").write_text("notes\n")
    base = ["localize", "--map", demo_map, "--images", imgs, "--queries", queries, "--out",
            tmp_path / "r.csv", "--overwrite", "--save-matches"]
    before = sha_tree(tmp_path)
    exit2(cli(*base, imgs), "is the input")
    exit2(cli(*base, imgs / "m"), "is inside the input")
    exit2(cli(*base, mine), "not match pictures")
    assert sha_tree(tmp_path) == before and not map_loads
    ours = tmp_path / "ours"
    assert cli(*base, ours)[0] == 0
    drawn = sha_tree(ours)
    (ours / name).write_bytes(b"stale")
    assert cli(*base, ours)[0] == 0 and sha_tree(ours) == drawn  # ours: replaced


@pytest.mark.fault("out_folders_hold_inputs")
def test_output_folders_never_hold_an_input(cli, map_copy, demo_data, tmp_path):
    """An output folder is swapped for the new one: a folder holding an input would lose it."""
    res = tmp_path / "r.csv"
    res.write_text(_RESULTS)
    gt = tmp_path / "gt.csv"
    gt.write_text("file,lat,lon\na.jpg,48.8606,2.3376\n")
    before = sha_tree(tmp_path)
    exit2(cli("evaluate", "--results", res, "--ground-truth", gt, "--integrity-out", tmp_path,
              "--overwrite"), "--integrity-out", "contains the input")
    assert sha_tree(tmp_path) == before
    q = tmp_path / "q.csv"
    q.write_text("file,lat,lon\n" + "".join(
        ",".join(r) + "\n" for r in list(csv.reader(open(demo_data / "coords.csv")))[1:4]))
    abl = tmp_path / "abl"
    abl.mkdir()
    (abl / "pri.csv").write_text("file,lat,lon\n")
    before = sha_tree(tmp_path)
    exit2(cli("ablate", "--map", map_copy, "--images", demo_data / "images", "--queries", q,
              "--priors", abl / "pri.csv", "--out", abl, "--top-p", "1"), "contains the input")
    assert sha_tree(tmp_path) == before
    npy = map_copy / "d.npy"  # descriptors kept inside an earlier map of ours
    np.save(npy, np.zeros((3, 8), np.float32))
    before = sha_tree(map_copy)
    exit2(cli("build-map", "--descriptors", npy, "--coords", q, "--out", map_copy,
              "--overwrite"), "contains the input")
    assert sha_tree(map_copy) == before
