"""Maps built from a folder of images record where their pictures are (folder + size/sha256
index): the debug view's reference panel shows them; a moved folder, a changed or a missing
picture gives one WARN naming it and never another picture in its place."""

from __future__ import annotations

import hashlib
import json
import logging
import shutil

import cv2
import numpy as np
import pytest

from vlm_vpr_ros.maps.map_images import SOURCE_INDEX, SourceImages, images_folder
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.runtime import debug_view

from source_pictures import build_from_demo, copy_with_pictures

N = 6
WARN = "vlm_vpr_ros.maps.map_images"


@pytest.fixture(scope="module")
def built(tmp_path_factory, demo_data):
    """(images folder, map, ids): a map built with ``build_map`` (``--images``) from a copy of
    six demo pictures in a temporary folder."""
    return build_from_demo(demo_data, tmp_path_factory.mktemp("source_images"), N,
                           local_features="none")


def _copy(built, tmp_path):
    """A private copy of the pictures and a map recording that copy as its source."""
    images, m, ids = built
    pics, mp, man = copy_with_pictures(images, m, tmp_path)
    return pics, mp, man, ids


def _thumb(path) -> np.ndarray:
    """The panel thumbnail computed independently: OpenCV read, RGB, area-resized to 360 px."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    w = int(round(rgb.shape[1] * debug_view.PANEL_HEIGHT / rgb.shape[0]))
    return cv2.resize(rgb, (w, debug_view.PANEL_HEIGHT), interpolation=cv2.INTER_AREA)


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == WARN and r.levelno == logging.WARNING]


def test_build_records_the_folder_and_every_picture(built):
    images, m, ids = built
    man = json.loads((m / "manifest.json").read_text())
    src = man["source_images"]
    assert src["folder"] == str(images.absolute()) and src["count"] == N
    assert src["index"] == SOURCE_INDEX and SOURCE_INDEX in man["files"]  # checked like a file
    index = np.load(m / SOURCE_INDEX, allow_pickle=False)  # rows id, bytes, sha256 by id
    assert [r.decode() for r in index["id"]] == sorted(ids)
    for row in index:
        data = (images / row["id"].decode()).read_bytes()
        assert row["bytes"] == len(data)
        assert row["sha256"].tobytes() == hashlib.sha256(data).digest()
    ReferenceMap.load(m, verify=True)  # the map (with its index) passes the full check
    # readers that do not check pictures are not handed the folder (unchanged for them)
    assert images_folder(m, man) is None and images_folder(m, man, source=True) == images


def test_debug_panel_shows_the_pictures_the_map_was_built_from(built):
    images, m, ids = built
    man = json.loads((m / "manifest.json").read_text())
    refs = debug_view.ReferenceImages.for_map(m, man)
    thumb, scale = refs.load(ids[2])
    expect = _thumb(images / ids[2])
    assert thumb.shape == expect.shape and np.abs(thumb.astype(int) - expect).max() <= 1
    query = np.full((480, 640, 3), 200, np.uint8)
    h, qw = debug_view.PANEL_HEIGHT, 480
    picture = debug_view.render(query, (thumb, scale), ["fix", ""], f"reference {ids[2]}")
    panel = picture[30:h, qw:qw + thumb.shape[1]]  # below the label: the reference's pixels
    assert np.abs(panel.astype(int) - expect[30:]).max() <= 1
    # before: the same map without the record (an old map) has the grey placeholder
    old = {k: v for k, v in man.items() if k != "source_images"}
    assert debug_view.ReferenceImages.for_map(m, old).load(ids[2]) is None
    empty = debug_view.render(query, None, ["fix", ""])
    assert np.abs(empty[30:h, qw:].astype(int) - expect[30:, :480]).mean() > 20


def test_moved_folder_warns_once_and_override_still_checks(built, tmp_path, caplog):
    pics, mp, man, ids = _copy(built, tmp_path)
    moved = tmp_path / "moved"
    pics.rename(moved)
    with caplog.at_level(logging.WARNING):
        refs = debug_view.ReferenceImages.for_map(mp, man)
        assert refs.folder is None and refs.load(ids[0]) is None
        assert debug_view.ReferenceImages.for_map(mp, man).load(ids[1]) is None
    warned = _warnings(caplog)
    assert len(warned) == 1 and str(pics) in warned[0] and "no longer there" in warned[0]
    # reference_images_dir names the new place: the same bytes, so the pictures are shown
    refs = debug_view.ReferenceImages.for_map(mp, man, str(moved))
    assert np.abs(refs.load(ids[0])[0].astype(int) - _thumb(moved / ids[0])).max() <= 1
    # ... but a folder holding other pictures under those names shows none of them
    other = tmp_path / "other"
    other.mkdir()
    for a, b in zip(ids, ids[1:] + ids[:1]):
        shutil.copy(moved / b, other / a)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        wrong = debug_view.ReferenceImages.for_map(mp, man, str(other))
        assert all(wrong.load(f) is None for f in ids)
    assert len(_warnings(caplog)) == N and all("changed since the map was built" in w
                                               for w in _warnings(caplog))


def test_changed_or_missing_picture_is_skipped_with_one_warning(built, tmp_path, caplog):
    pics, mp, man, ids = _copy(built, tmp_path)
    shutil.copy(pics / ids[1], pics / ids[0])  # replaced by another picture
    data = bytearray((pics / ids[2]).read_bytes())  # same size, a few bytes differ
    data[len(data) // 2:len(data) // 2 + 8] = bytes(8)
    (pics / ids[2]).write_bytes(bytes(data))
    (pics / ids[3]).unlink()
    with caplog.at_level(logging.WARNING):
        for _ in range(2):  # a new view (no cache) does not warn again
            refs = debug_view.ReferenceImages.for_map(mp, man)
            assert [refs.load(f) is None for f in ids] == [True, False, True, True, False,
                                                           False]
    warned = _warnings(caplog)
    assert len(warned) == 3
    assert str(pics / ids[0]) in warned[0] and "changed" in warned[0]
    assert str(pics / ids[2]) in warned[1] and "changed" in warned[1]
    assert str(pics / ids[3]) in warned[2] and "missing" in warned[2]
    # a picture the index does not list (added to the folder or the map later): not shown
    shutil.copy(pics / ids[4], pics / "new.jpg")
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert SourceImages.for_map(mp, man).read("new.jpg") is None
    assert len(_warnings(caplog)) == 1 and "not in the index" in _warnings(caplog)[0]


def test_malformed_record_warns_and_shows_nothing(built, tmp_path, caplog):
    _, mp, man, ids = _copy(built, tmp_path)
    for bad in ("pictures", {"folder": "relative/path", "index": SOURCE_INDEX},
                {"folder": str(tmp_path), "index": "not_listed.json"}):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            refs = debug_view.ReferenceImages.for_map(tmp_path / str(len(str(bad))),
                                                      {**man, "source_images": bad})
            assert refs.folder is None and refs.load(ids[0]) is None
        assert len(_warnings(caplog)) == 1 and "malformed" in _warnings(caplog)[0]
    # the index file itself altered: refused (it is checked like every file the map lists)
    (mp / SOURCE_INDEX).write_text("{}")
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert debug_view.ReferenceImages.for_map(mp, man).load(ids[0]) is None
    assert len(_warnings(caplog)) == 1 and "unusable" in _warnings(caplog)[0]


def test_teach_map_keeps_its_pictures_not_the_build_folder(built, tmp_path):
    """``build-map --bag`` builds from a scratch folder, then moves the pictures into the map:
    the record of the scratch folder is dropped (the map's own images/ are used)."""
    from vlm_vpr_ros.maps.map_images import attach_images, verify_images

    pics, mp, man, ids = _copy(built, tmp_path)
    attach_images(mp, pics)
    after = json.loads((mp / "manifest.json").read_text())
    assert "source_images" not in after and SOURCE_INDEX not in after["files"]
    assert SOURCE_INDEX in after["retired"] and verify_images(mp) == N
    refs = debug_view.ReferenceImages.for_map(mp, after)
    assert refs.folder == mp / "images" and refs.load(ids[0]) is not None
