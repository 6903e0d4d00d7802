"""Corrupt map folders and CSV inputs: exit 2 with one line naming the problem."""

from __future__ import annotations

import hashlib
import logging
import json
import os
import shutil

import numpy as np
import pytest

from faults.conftest import exit2, sha_tree


def _manifest(m):
    return json.loads((m / "manifest.json").read_text())


def _edit(m, fn):
    man = _manifest(m)
    fn(man)
    (m / "manifest.json").write_text(json.dumps(man))


def _rehash(m, rel):
    """Make a tampered file pass the size/sha check, so the reader itself must cope."""
    data = (m / rel).read_bytes()
    _edit(m, lambda man: man["files"].__setitem__(
        rel, {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}))


def _localize(cli, m, demo_data, queries, tmp_path):
    before = sha_tree(m)
    res = cli("localize", "--map", m, "--images", demo_data / "images", "--queries", queries,
              "--out", tmp_path / "r.csv")
    assert sha_tree(m) == before and not (tmp_path / "r.csv").exists()
    return res


@pytest.mark.fault("map_manifest_truncated")
def test_manifest_truncated(cli, map_copy, demo_data, queries, tmp_path):
    p = map_copy / "manifest.json"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    exit2(_localize(cli, map_copy, demo_data, queries, tmp_path), "corrupt manifest")


def _case(case, *values):
    return pytest.param(*values, marks=pytest.mark.fault(case), id=case)


@pytest.mark.parametrize("edit,needle", [
    _case("map_files_list", lambda m: m.__setitem__("files", list(m["files"])), "'files'"),
    _case("map_submaps_int", lambda m: m.__setitem__("submaps", 3), "'submaps'"),
    _case("map_partition_str", lambda m: m.__setitem__("partition", "kmeans"), "'partition'"),
    _case("map_submap_no_index", lambda m: m["submaps"][0]["files"].pop("index"),
          "'submaps[0].files' lacks 'index'"),
    _case("map_file_outside",
          lambda m: m["submaps"][0]["files"].__setitem__("ids", "../ids.json"),
          "points outside the map folder"),
])
def test_manifest_structure(cli, map_copy, demo_data, queries, tmp_path, edit, needle):
    _edit(map_copy, edit)
    exit2(_localize(cli, map_copy, demo_data, queries, tmp_path), needle)


@pytest.mark.fault("map_ids_outside")
def test_ids_outside_images_folder(cli, map_copy, demo_data, queries, tmp_path):
    rel = _manifest(map_copy)["submaps"][0]["files"]["ids"]
    v2 = rel.endswith(".npy")  # format v2: a fixed-width bytes array; v1: a JSON list
    ids = ([i.decode() for i in np.load(map_copy / rel)] if v2
           else json.loads((map_copy / rel).read_text()))
    for bad in ("../../etc/passwd", "/etc/passwd"):
        ids[0] = bad
        if v2:
            from vlm_vpr_ros.maps.store import encode_ids

            np.save(map_copy / rel, encode_ids(ids), allow_pickle=False)
        else:
            (map_copy / rel).write_text(json.dumps(ids))
        _rehash(map_copy, rel)
        exit2(_localize(cli, map_copy, demo_data, queries, tmp_path),
              "points outside the images folder")


@pytest.mark.fault("map_npy_truncated")
def test_npy_truncated(cli, map_copy, demo_data, queries, tmp_path):
    rel = _manifest(map_copy)["submaps"][1]["files"]["coords"]
    p = map_copy / rel
    p.write_bytes(p.read_bytes()[:-7])
    exit2(_localize(cli, map_copy, demo_data, queries, tmp_path), "truncated or modified")


@pytest.mark.parametrize("key,needle", [
    _case("map_npy_garbage", "coords", "cannot read"),
    _case("map_faiss_garbage", "index", "cannot read FAISS index"),
])
def test_submap_file_garbage(cli, map_copy, demo_data, queries, tmp_path, key, needle):
    rel = _manifest(map_copy)["submaps"][0]["files"][key]
    (map_copy / rel).write_bytes(os.urandom(300))
    _rehash(map_copy, rel)
    exit2(_localize(cli, map_copy, demo_data, queries, tmp_path), needle)


@pytest.mark.fault("map_state_garbage")
def test_state_garbage(cli, map_copy, demo_data, queries, tmp_path):
    (map_copy / "descriptor_state.npz").write_bytes(b"PK\x03\x04" + os.urandom(500))
    _rehash(map_copy, "descriptor_state.npz")
    exit2(_localize(cli, map_copy, demo_data, queries, tmp_path),
          "cannot read descriptor_state.npz")


@pytest.mark.fault("map_up_to_date_images_changed")
def test_up_to_date_notices_changed_images(cli, tmp_path, demo_data):
    from vlm_vpr_ros.mapping.build_images import build_map

    images = tmp_path / "images"
    shutil.copytree(demo_data / "images", images)
    names = sorted(p.name for p in images.iterdir())[:12]
    coords = tmp_path / "c.csv"
    src = {r.split(",")[0]: r for r in (demo_data / "coords.csv").read_text().splitlines()[1:]}
    coords.write_text("file,lat,lon\n" + "\n".join(src[n] for n in names) + "\n")
    args = ("build-map", "--images", images, "--coords", coords, "--out", tmp_path / "m",
            "--descriptor", "vlad_rootsift_fast", "--partition", "none")
    assert cli(*args)[0] == 0
    assert cli(*args)[0] == 0 and "up to date" in cli.text
    shutil.copy(images / names[1], images / names[0])  # replaced by other bytes
    exit2(cli(*args), "out of date")
    (images / names[0]).unlink()  # deleted
    exit2(cli(*args), "out of date")
    assert cli(*args, "--overwrite")[0] == 0  # rebuilt without the deleted image
    assert build_map(images, coords, tmp_path / "m", descriptor="vlad_rootsift_fast",
                     partition="none", progress=False).manifest["source"]["skipped"] == [names[0]]


# -- CSV readers ---------------------------------------------------------------------------------
def _coords(tmp_path, demo_data, body: str, name="c.csv", prefix=""):
    p = tmp_path / name
    p.write_text(prefix + "file,lat,lon\n" + body, encoding="utf-8")
    return p


def _build(cli, tmp_path, demo_data, coords):
    return cli("build-map", "--images", demo_data / "images", "--coords", coords, "--out",
               tmp_path / "m", "--descriptor", "vlad_rootsift_fast", "--partition", "none")


@pytest.fixture
def two(demo_data):
    return sorted(p.name for p in (demo_data / "images").iterdir())[:2]


@pytest.mark.fault("csv_coords_lat_999")
def test_coords_lat_999(cli, tmp_path, demo_data, two):
    c = _coords(tmp_path, demo_data, f"{two[0]},10,10\n{two[1]},999,10\n")
    exit2(_build(cli, tmp_path, demo_data, c), "c.csv:3", "latitude 999 out of range")
    assert not (tmp_path / "m").exists()


@pytest.mark.fault("csv_coords_conflict")
def test_coords_conflict(cli, tmp_path, demo_data, two):
    c = _coords(tmp_path, demo_data, f"{two[0]},10,10\n{two[1]},5,5\n{two[0]},11,10\n")
    exit2(_build(cli, tmp_path, demo_data, c), "lines 2 and 4")


@pytest.mark.fault("csv_coords_repeat")
def test_coords_repeat(tmp_path, demo_data, two, caplog):
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv

    c = _coords(tmp_path, demo_data, f"{two[0]},10,10\n{two[1]},5,5\n{two[0]},10,10\n")
    assert read_coords_csv(c) == [(two[0], 10.0, 10.0), (two[1], 5.0, 5.0)]
    assert "lines 2, 4" in caplog.text


@pytest.mark.fault("csv_coords_outside")
def test_coords_outside(cli, tmp_path, demo_data, two):
    for bad in ("../secret.jpg", "/etc/x.jpg", "a/../../b.jpg"):
        c = _coords(tmp_path, demo_data, f"{two[0]},10,10\n{bad},5,5\n")
        exit2(_build(cli, tmp_path, demo_data, c), "c.csv:3", "outside the images folder")


@pytest.mark.fault("csv_bom")
def test_bom_accepted(tmp_path, demo_data, two):
    from vlm_vpr_ros.evaluation.metrics import read_ground_truth
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv
    from vlm_vpr_ros.priors.simple import read_prior_csv

    c = _coords(tmp_path, demo_data, f"{two[0]},10,10\n", prefix="\ufeff")
    assert c.read_bytes().startswith(b"\xef\xbb\xbf")
    assert read_coords_csv(c) == [(two[0], 10.0, 10.0)]
    assert read_ground_truth(c) == {two[0]: (10.0, 10.0)}
    assert read_prior_csv(c) == {two[0]: (10.0, 10.0)}


@pytest.mark.fault("csv_gt_lat_999")
def test_gt_lat_999(cli, tmp_path):
    (tmp_path / "r.csv").write_text("file,lat,lon,flags,submap\na.jpg,1,1,,\n")
    (tmp_path / "gt.csv").write_text("file,lat,lon\na.jpg,999,1\n")
    exit2(cli("evaluate", "--results", tmp_path / "r.csv", "--ground-truth",
              tmp_path / "gt.csv"), "gt.csv:2", "latitude 999")


@pytest.mark.fault("csv_gt_conflict")
def test_gt_conflict(cli, tmp_path):
    (tmp_path / "r.csv").write_text("file,lat,lon\na.jpg,1,1\n")
    (tmp_path / "gt.csv").write_text("file,lat,lon\na.jpg,1,1\nb.jpg,2,2\na.jpg,3,1\n")
    exit2(cli("evaluate", "--results", tmp_path / "r.csv", "--ground-truth",
              tmp_path / "gt.csv"), "lines 2 and 4")


@pytest.mark.fault("csv_priors_conflict")
def test_priors_conflict(tmp_path):
    from vlm_vpr_ros.errors import DataError
    from vlm_vpr_ros.priors import create_prior_provider

    (tmp_path / "p.csv").write_text("file,lat,lon\na.jpg,1,1\na.jpg,2,1\n")
    with pytest.raises(DataError, match="lines 2 and 3"):
        create_prior_provider("recorded", {"path": str(tmp_path / "p.csv")})


@pytest.mark.fault("csv_answers_conflict")
def test_answers_conflict(cli, tmp_path):
    (tmp_path / "a.csv").write_text('filename,response\na.jpg,"1, 2"\na.jpg,"3, 4"\n')
    (tmp_path / "gt.csv").write_text("file,lat,lon\na.jpg,1,1\n")
    exit2(cli("priors", "score", "--answers", tmp_path / "a.csv", "--ground-truth",
              tmp_path / "gt.csv"), "lines 2 and 3")


@pytest.mark.fault("csv_results_binary")
def test_results_binary(cli, tmp_path):
    (tmp_path / "r.csv").write_bytes(b"file,lat,lon\n" + b"\x00\x01\x02" * 50)
    (tmp_path / "gt.csv").write_text("file,lat,lon\na.jpg,1,1\n")
    exit2(cli("evaluate", "--results", tmp_path / "r.csv", "--ground-truth",
              tmp_path / "gt.csv"), "r.csv")


@pytest.mark.fault("csv_latin1")
def test_latin1(cli, tmp_path, demo_data):
    c = tmp_path / "c.csv"
    c.write_bytes("file,lat,lon\ncaf\u00e9.jpg,1,1\n".encode("latin-1"))
    exit2(_build(cli, tmp_path, demo_data, c), "malformed CSV")


# -- answers --------------------------------------------------------------------------------------
@pytest.mark.fault("answer_1e400")
def test_answer_overflow():
    from vlm_vpr_ros.priors.parsing import PARSER_MODES, parse_answer

    for text in ('{"latitude": 1e400, "longitude": 1}', "Latitude: 1e400, Longitude: 1",
                 '{"latitude": "1e400", "longitude": "1"}'):
        for mode in PARSER_MODES[:2]:
            p = parse_answer(text, mode)  # strict reads no prose: "no_coordinates" there
            assert not p.ok and p.reason in ("out_of_range", "no_coordinates"), (text, mode)
        assert parse_answer(text, "robust").reason == "out_of_range"


@pytest.mark.fault("answer_scientific")
def test_answer_scientific():
    from vlm_vpr_ros.priors.parsing import parse_answer

    for text in ('{"latitude": 0.45e2, "longitude": 0.1e1}', "Latitude: 4.5E1, Longitude: 1",
                 '{"latitude": "0.45e2", "longitude": "1"}', "coordinates: 0.45e2, 1.0"):
        p = parse_answer(text)
        assert p.ok and (p.lat, p.lon) == (45.0, 1.0), (text, p)
    assert np.isclose(parse_answer("Latitude: 0.1e2 N, Longitude: 2 E").lat, 10.0)


@pytest.mark.fault("disk_full_descriptors_manifest")
def test_descriptors_build_resumes_after_failing_at_its_manifest(cli, tmp_path, monkeypatch):
    """`build-map --descriptors`: ENOSPC at the manifest, after the finished submap files
    moved into the staged map; the same command then resumes and finishes."""
    from vlm_vpr_ros.files import atomic
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    rng = np.random.default_rng(5)
    desc = rng.normal(size=(40, 512)).astype(np.float32)
    np.save(tmp_path / "d.npy", desc / np.linalg.norm(desc, axis=1, keepdims=True))
    pos = rng.uniform([45, 7], [45.1, 7.1], size=(40, 2))
    (tmp_path / "c.csv").write_text("file,lat,lon\n" + "".join(
        f"r{i}.jpg,{a:.7f},{b:.7f}\n" for i, (a, b) in enumerate(pos)))
    real = atomic.atomic_write_text

    def full(path, text, *a, **k):
        if str(path).endswith("manifest.json"):
            raise atomic.OutputError(f"cannot write {path}: No space left on device")
        return real(path, text, *a, **k)

    args = ("build-map", "--descriptors", tmp_path / "d.npy", "--coords", tmp_path / "c.csv",
            "--out", tmp_path / "m", "--descriptor", "cosplace", "--clusters", "3",
            "--index", "flat")
    monkeypatch.setattr(atomic, "atomic_write_text", full)
    exit2(cli(*args), "No space left on device")
    assert not (tmp_path / "m").exists()
    monkeypatch.setattr(atomic, "atomic_write_text", real)  # space freed
    rc, _, errors = cli(*args)  # before the fix: exit 2 "cannot write ... k000.faiss"
    assert rc == 0, errors
    m = ReferenceMap.load(tmp_path / "m", verify=True)
    assert m.n_references == 40 and not (tmp_path / ".m.partial").exists()


@pytest.mark.fault("map_field_types_more")
def test_more_manifest_fields_of_another_type(cli, map_copy, demo_data, queries, tmp_path):
    """Fields read after the load (map info, map remove, localize): exit 2 naming the field,
    never exit 1 'internal error' (AttributeError, ValueError, TypeError)."""
    original = (map_copy / "manifest.json").read_text()
    (tmp_path / "ids.txt").write_text("x\n")
    cases = [
        (lambda m: m.__setitem__("index_params", 5), "'index_params'", "info"),
        (lambda m: m.__setitem__("index_params", {"rerank_factor": "8"}),
         "'index_params.rerank_factor'", "info"),
        (lambda m: m.__setitem__("generation", "x"), "'generation'", "remove"),
        (lambda m: m.__setitem__("source", []), "'source'", "info"),
        (lambda m: m["descriptor"].pop("name"), "'descriptor.name'", "info"),
        (lambda m: m["submaps"][0].__setitem__("recall", 3), "'submaps[0].recall'", "info"),
        (lambda m: m.__setitem__("retired", ["../../outside.txt"]), "'retired[0]'", "remove"),
        (lambda m: m.__setitem__("calibration", 7), "'calibration'", "info"),
    ]
    for edit, needle, command in cases:
        (map_copy / "manifest.json").write_text(original)
        _edit(map_copy, edit)
        args = (("map", "info", map_copy) if command == "info" else
                ("map", "remove", map_copy, "--ids", tmp_path / "ids.txt"))
        exit2(cli(*args), needle)
    exit2(_localize(cli, map_copy, demo_data, queries, tmp_path), "'calibration'")


# -- round 5 (issue 43) --------------------------------------------------------------------------
@pytest.mark.fault("map_readd_same_name")
def test_a_picture_readded_under_a_removed_name_is_never_the_old_one(cli, demo_data,
                                                                       tmp_path, caplog):
    """Before: the build's record still vouched for the old file, so the debug view and the
    calibration read the old picture for the new reference."""
    from source_pictures import build_from_demo
    from vlm_vpr_ros.maps.map_images import SourceImages

    pics, m, ids = build_from_demo(demo_data, tmp_path, 5, local_features="none")
    x, old = ids[0], (pics / ids[0]).read_bytes()
    (tmp_path / "x.txt").write_text(x + "\n")
    assert cli("map", "remove", m, "--ids", tmp_path / "x.txt")[0] == 0
    other = sorted(p.name for p in (demo_data / "images").iterdir() if p.name not in ids)[0]
    new = tmp_path / "new"
    new.mkdir()
    shutil.copy(demo_data / "images" / other, new / x)
    (tmp_path / "add.csv").write_text(f"file,lat,lon\n{x},37.77,-122.42\n")
    assert cli("map", "add", m, "--images", new, "--coords", tmp_path / "add.csv")[0] == 0
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        data = SourceImages.for_map(m, _manifest(m)).read(x)
    assert data is None and (pics / x).read_bytes() == old  # not the build folder's old x
    assert "not in the index" in caplog.text


@pytest.mark.fault("calibrate_pictures_gone")
def test_calibrate_without_the_pictures_keeps_the_calibration(cli, demo_data, tmp_path):
    """Before: exit 0 with a WARN, the calibration under several conditions replaced by a
    full-size one, so no answer could reach p_correct 0.99 any more."""
    from source_pictures import build_from_demo
    from vlm_vpr_ros.localization.verification.p_correct import load_doc
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    pics, m, ids = build_from_demo(demo_data, tmp_path, 6,
                                   calibration_conditions="full,fit480x360")
    shutil.move(str(pics), tmp_path / "moved")
    before = sha_tree(m)
    exit2(cli("calibrate", "--map", m, "--conditions", "default"), str(pics),
          "fit640x480", "old calibration was kept")
    assert sha_tree(m) == before
    (tmp_path / "rm.txt").write_text(ids[0] + "\n")
    assert cli("map", "remove", m, "--ids", tmp_path / "rm.txt")[0] == 0
    assert load_doc(ReferenceMap.load(m))["conditions"] == ["full", "fit480x360"]
    assert "keeps its earlier calibration" in cli.text
