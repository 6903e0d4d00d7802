"""Issue 43: the record of the pictures a map was built from follows ``map remove`` and
``map add``: a different picture added under a removed reference's name is never read as the
old one (the old record vouched for the old file)."""

from __future__ import annotations

import csv
import hashlib
import json
import logging
import shutil

import numpy as np
import pytest

from vlm_vpr_ros.mapping.edit import add_references, remove_references
from vlm_vpr_ros.maps.map_images import SourceImages
from vlm_vpr_ros.maps.reference_map import ReferenceMap

from source_pictures import build_from_demo


@pytest.fixture
def built(tmp_path, demo_data):
    return build_from_demo(demo_data, tmp_path, 6, local_features="none")


def _pictures(m):
    man = json.loads((m / "manifest.json").read_text())
    return SourceImages.for_map(m, man), man


def _row(demo_data, name):
    rows = {r["file"]: r for r in csv.DictReader(open(demo_data / "coords.csv"))}
    return float(rows[name]["lat"]), float(rows[name]["lon"])


def test_a_picture_added_under_a_removed_name_is_never_the_old_one(built, demo_data,
                                                                    tmp_path, caplog):
    pics, m, ids = built
    x = ids[0]
    old = (pics / x).read_bytes()
    remove_references(m, [x])
    src, man = _pictures(m)
    assert src.read(x) is None and src.read(ids[1]) == (pics / ids[1]).read_bytes()
    index = np.load(m / man["source_images"]["index"], allow_pickle=False)
    assert x.encode() not in set(index["id"]) and len(index) == 5
    # another picture named x, added from another folder; the build folder keeps the old x
    other = sorted(p.name for p in (demo_data / "images").iterdir() if p.name not in ids)[0]
    new_dir = tmp_path / "new"
    new_dir.mkdir()
    shutil.copy(demo_data / "images" / other, new_dir / x)
    assert (new_dir / x).read_bytes() != old
    add_references(m, new_dir, [(x, *_row(demo_data, other))], progress=False)
    src, man = _pictures(m)
    with caplog.at_level(logging.WARNING, logger="vlm_vpr_ros.maps.map_images"):
        assert src.read(x) is None  # not the build folder's old picture
    assert "not in the index" in caplog.text
    ReferenceMap.load(m, verify=True)  # the edited map (and its record) pass the full check
    assert (pics / x).read_bytes() == old  # the user's folder untouched


def test_a_picture_added_from_the_recorded_folder_is_recorded_as_it_is_now(built, demo_data):
    pics, m, ids = built
    x = ids[0]
    remove_references(m, [x])
    other = sorted(p.name for p in (demo_data / "images").iterdir() if p.name not in ids)[0]
    shutil.copy(demo_data / "images" / other, pics / x)  # the folder's x is now another one
    add_references(m, pics, [(x, *_row(demo_data, other))], progress=False)
    src, man = _pictures(m)
    data = src.read(x)
    assert data == (demo_data / "images" / other).read_bytes()
    index = np.load(m / man["source_images"]["index"], allow_pickle=False)
    row = index[list(index["id"]).index(x.encode())]
    assert row["sha256"].tobytes() == hashlib.sha256(data).digest() and len(index) == 6
    assert man["source_images"]["count"] == 6
    ReferenceMap.load(m, verify=True)
