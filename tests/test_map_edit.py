"""``vlm-vpr map add`` / ``map remove`` on the shipped demo images (no ../shared needed).

The independent reference for an add is a one-shot map assembled from the same references
described by the same descriptor state: a grown map must answer every query exactly like it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil

import numpy as np
import pytest

from teach_bags import Place, write_teach_bag
from vlm_vpr_ros.cli import main
from vlm_vpr_ros.evaluation.demo import make_query
from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.localization.localizer import Localizer
from vlm_vpr_ros.mapping.assemble import assemble_map
from vlm_vpr_ros.mapping.coords_csv import read_coords_csv
from vlm_vpr_ros.mapping import edit as map_edit
from vlm_vpr_ros.maps.map_images import verify_images
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
from vlm_vpr_ros.priors.provider import Prior, PriorResult

FAST = "vlad_rootsift_fast"


def cli(caplog, *args) -> tuple[int, str]:
    caplog.clear()
    with caplog.at_level(logging.ERROR):
        rc = main([str(a) for a in args])
    return rc, "\n".join(r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR)


def _csv(path, rows):
    path.write_text("file,lat,lon\n" + "".join(f"{f},{a!r},{b!r}\n" for f, a, b in rows))
    return path


def _files(map_dir):
    return {p.relative_to(map_dir).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in map_dir.rglob("*") if p.is_file() and p.name != ".edit.lock"}


@pytest.fixture(scope="module")
def halves(demo_data, demo_half_map):
    """(rows, first-half map (conftest), queries); tests copy the map before editing it."""
    rows, half = demo_half_map
    rng = np.random.default_rng(3)
    queries = [make_query(load_image(demo_data / "images" / f), rng) for f, _, _ in rows[::4]]
    return rows, half, queries


@pytest.fixture()
def half_map(halves, tmp_path):
    out = tmp_path / "map"
    shutil.copytree(halves[1], out)
    return out


def _answers(pipe, descs, priors=None):
    out = []
    for i, d in enumerate(descs):
        pr = None if priors is None else PriorResult(Prior(*priors[i], "gt"), "gt")
        h = pipe.localize_descriptor(d, pr)
        out.append((h.ref_id, round(h.lat, 7), round(h.lon, 7)))
    return out


def test_add_equals_one_shot_build(halves, half_map, demo_data, tmp_path, caplog):
    rows, half, queries = halves
    state_before = (half_map / "descriptor_state.npz").read_bytes()
    before = _files(half_map)
    rc, err = cli(caplog, "map", "add", half_map, "--images", demo_data / "images", "--coords",
                  _csv(tmp_path / "h2.csv", rows[36:]))
    assert rc == 0, err
    grown = ReferenceMap.load(half_map, verify=True)
    assert grown.n_references == len(rows) and grown.manifest["generation"] == 1
    assert (half_map / "descriptor_state.npz").read_bytes() == state_before  # state kept
    after = _files(half_map)
    untouched = {k for k in before if k in after and before[k] == after[k]}
    # only the submaps that received references were rewritten
    rewritten = {e["id"] for e in grown.manifest["submaps"] if ".g1." in e["files"]["index"]}
    for e in grown.manifest["submaps"]:
        if e["id"] not in rewritten:
            assert set(e["files"].values()) <= untouched
    assert rewritten and len(rewritten) <= len(grown.submaps)
    assert not any(".g0." in k or k in before for k in after if ".g1." in k)
    assert "fingerprint" not in grown.manifest["source"]
    # the independent reference: one-shot map of all references with the same descriptor
    # (first half: the vectors build-map computed; second half: described here, not by add)
    pipe = LocalizationPipeline.open(half_map)
    desc = pipe.descriptor
    first = ReferenceMap.load(half)
    by_id = dict(zip(first.all_ids(), first.all_descriptors()))
    feats = np.concatenate([np.stack([by_id[f] for f, _, _ in rows[:36]]), desc.describe(
        [load_image(demo_data / "images" / f) for f, _, _ in rows[36:]])])
    coords = np.array([[a, b] for _, a, b in rows])
    once = assemble_map(feats, coords, [f for f, _, _ in rows], dict(grown.descriptor_identity),
                        grown.descriptor_state, "kmeans", 6)
    ref = LocalizationPipeline(once, desc, Localizer(once, pipe.localizer.config))
    qd = [desc.describe_one(q) for q in queries]
    assert _answers(pipe, qd) == _answers(ref, qd)  # every query, no prior: global search
    # the grown map's stored vectors are the one-shot descriptors
    got = dict(zip(grown.all_ids(), grown.all_descriptors()))
    for f, v in zip([f for f, _, _ in rows], feats):
        np.testing.assert_allclose(got[f], v, atol=1e-5)
    # with a prior each reference lies in a submap whose centroid is its members' mean
    truth = [(a, b) for _, a, b in rows[::4]]
    hits = sum(a[0] == f for a, (f, _, _) in zip(_answers(pipe, qd, truth), rows[::4]))
    assert hits >= 0.8 * len(qd)


def test_far_references_make_a_new_submap(half_map, demo_data, tmp_path):
    rows = read_coords_csv(demo_data / "coords.csv")
    m0 = ReferenceMap.load(half_map)
    # two images placed on a remote island: no submap of the map reaches there
    far = [(rows[40][0], -54.42, 3.36), (rows[41][0], -54.4201, 3.3601)]
    res = map_edit.add_references(half_map, demo_data / "images", far, progress=False)
    assert res.created and len(res.created) == 1 and res.changed == res.created
    m1 = ReferenceMap.load(half_map)
    assert len(m1.submaps) == len(m0.submaps) + 1
    new = m1.submaps[m1.submap_index(res.created[0])]
    assert sorted(new.ids) == sorted(f for f, _, _ in far)
    assert new.centroid == pytest.approx((-54.42005, 3.36005), abs=1e-4)


def test_remove_restores_the_half_map(halves, half_map, demo_data, tmp_path, caplog):
    rows, half, queries = halves
    ids_file = tmp_path / "ids.txt"
    ids_file.write_text("# added\n" + "\n".join(f for f, _, _ in rows[36:44]) + "\n")
    assert cli(caplog, "map", "add", half_map, "--images", demo_data / "images", "--coords",
               _csv(tmp_path / "h2.csv", rows[36:44]))[0] == 0
    rc, err = cli(caplog, "map", "remove", half_map, "--ids", ids_file)
    assert rc == 0, err
    m = ReferenceMap.load(half_map)
    assert sorted(m.all_ids()) == sorted(f for f, _, _ in rows[:36])
    assert m.manifest["generation"] == 2
    a, b = LocalizationPipeline.open(half_map), LocalizationPipeline.open(half)
    qd = [a.descriptor.describe_one(q) for q in queries[:20]]
    assert [x[0] for x in _answers(a, qd)] == [x[0] for x in _answers(b, qd)]
    # unknown ids change nothing; removing everything is refused
    before = _files(half_map)
    (tmp_path / "bad.txt").write_text("nope.jpg\n")
    rc, err = cli(caplog, "map", "remove", half_map, "--ids", tmp_path / "bad.txt")
    assert rc == 2 and "nope.jpg" in err and _files(half_map) == before
    _csv(tmp_path / "all.csv", rows[:36])
    rc, err = cli(caplog, "map", "remove", half_map, "--ids", tmp_path / "all.csv")
    assert rc == 2 and "empty map" in err and _files(half_map) == before


def test_other_descriptor_and_duplicates_are_refused(half_map, demo_data, tmp_path, caplog):
    rows = read_coords_csv(demo_data / "coords.csv")
    before = _files(half_map)
    rc, err = cli(caplog, "map", "add", half_map, "--images", demo_data / "images", "--coords",
                  _csv(tmp_path / "h2.csv", rows[36:40]), "--descriptor", "vlad_rootsift")
    assert rc == 2 and "vlad_rootsift_fast" in err and "'vlad_rootsift' was requested" in err
    rc, err = cli(caplog, "map", "add", half_map, "--images", demo_data / "images", "--coords",
                  _csv(tmp_path / "dup.csv", rows[30:40]))
    assert rc == 2 and "already in the map" in err
    rc, err = cli(caplog, "map", "add", half_map, "--images", demo_data / "images", "--coords",
                  tmp_path / "h2.csv", "--descriptor-option", "pca_dim=64")
    assert rc == 2 and "pca_dim=128" in err and "refused: pca_dim=64" in err
    assert _files(half_map) == before


def test_failed_add_leaves_the_map_intact(half_map, demo_data, tmp_path, monkeypatch):
    rows = read_coords_csv(demo_data / "coords.csv")
    before = _files(half_map)

    def boom(*a, **k):
        raise OSError("disk full (injected)")

    monkeypatch.setattr(map_edit, "finish_manifest", boom)  # after the submaps were written
    with pytest.raises(OSError, match="injected"):
        map_edit.add_references(half_map, demo_data / "images", rows[36:42], progress=False)
    assert _files(half_map) == before
    ReferenceMap.load(half_map, verify=True)


def test_teach_map_grows_by_a_second_drive(demo_data, tmp_path, caplog, monkeypatch):
    rows = read_coords_csv(demo_data / "coords.csv")[:16]
    places = [Place(load_image(demo_data / "images" / f)[::2, ::2].copy(), a, b)
              for f, a, b in rows]
    d1 = write_teach_bag(tmp_path / "drive1", places[:8], standstill=2)
    d2 = write_teach_bag(tmp_path / "drive2", places[8:], gaps=(4,), t0=1_800_000_000 * 10**9)
    assert cli(caplog, "build-map", "--bag", d1.path, "--out", tmp_path / "m", "--descriptor",
               FAST, "--descriptor-option", "max_side=320", "--clusters", "3")[0] == 0
    # a mistyped map: refused before any folder is made (before: nope/ and its staging)
    rc, err = cli(caplog, "map", "add", tmp_path / "nope" / "m", "--bag", d2.path)
    assert rc == 2 and "map folder not found" in err and not (tmp_path / "nope").exists()
    rc, err = cli(caplog, "map", "add", tmp_path / "m", "--bag", d2.path)
    assert rc == 0, err
    m = ReferenceMap.load(tmp_path / "m")
    assert m.n_references == 16 and verify_images(tmp_path / "m") == 16
    assert sum(i.startswith("drive2/") for i in m.all_ids()) == 8
    assert not list((tmp_path / "m").glob(".add*"))
    drop = [i for i in m.all_ids() if i.startswith("drive1/")][:3]
    (tmp_path / "ids.txt").write_text("\n".join(drop))
    assert cli(caplog, "map", "remove", tmp_path / "m", "--ids", tmp_path / "ids.txt")[0] == 0
    assert verify_images(tmp_path / "m") == 13
    man = json.loads((tmp_path / "m" / "manifest.json").read_text())
    idx = man["images"]
    assert idx["count"] == 13 and idx["index"].endswith(".g2.json")
    # the removed images stay one generation (a reader of the previous manifest may show
    # them), listed in `retired`, and the next edit deletes them
    gone = [f"images/{i}" for i in drop]
    assert set(gone) <= set(man["retired"]) and not set(gone) & set(man["files"])
    assert all((tmp_path / "m" / g).is_file() for g in gone)
    (tmp_path / "ids.txt").write_text(m.all_ids()[-1])
    assert cli(caplog, "map", "remove", tmp_path / "m", "--ids", tmp_path / "ids.txt")[0] == 0
    assert not any((tmp_path / "m" / g).exists() for g in gone)
    assert verify_images(tmp_path / "m") == 12
    monkeypatch.setenv("VLM_VPR_LOCK_WAIT_S", "0")
    with pytest.raises(MapError, match="being written by another process"):
        with map_edit.edit_lock(tmp_path / "m"):
            with map_edit.edit_lock(tmp_path / "m"):
                pass
