"""The map's change notice (vlm_vpr_ros/maps/watch.py): a query stats a map file again only when
the folder reported a change (or a second passed), and a change made before a query is still
seen by that query."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.localization.localizer import Localizer
from vlm_vpr_ros.mapping.assemble import assemble_map
from vlm_vpr_ros.maps import store, watch
from vlm_vpr_ros.maps.reference_map import ReferenceMap

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="inotify: Linux")

MOUNTINFO = """\
22 1 254:1 / / rw,relatime shared:1 - ext4 /dev/vda rw
30 22 0:40 / /mnt/fleet\\040maps rw shared:9 - nfs4 srv:/maps rw
31 30 0:41 / /mnt/fleet\\040maps/local rw shared:10 - xfs /dev/vdb rw
32 22 0:42 / /srv rw shared:11 - fuse.sshfs host:/srv rw
"""


def test_filesystem_type_is_the_longest_mount_point_holding_the_path():
    ft = watch.filesystem_type
    assert ft("/home/robot/map", MOUNTINFO) == "ext4"
    assert ft("/mnt/fleet maps/sf", MOUNTINFO) == "nfs4"
    assert ft("/mnt/fleet maps/local/sf", MOUNTINFO) == "xfs"
    assert ft("/mnt/fleet mapsX/sf", MOUNTINFO) == "ext4"  # a prefix is not a parent
    assert ft("/srv/map", MOUNTINFO) == "fuse.sshfs"
    assert ft("/x", "") == ""


def test_generation_changes_on_every_kind_of_change_and_only_then(tmp_path, monkeypatch):
    monkeypatch.setattr(watch, "REFRESH_S", 3600.0)
    f = tmp_path / "a.npy"
    f.write_bytes(b"0" * 4096)
    w = watch.FolderWatch([tmp_path])
    if not w.active:
        pytest.skip("no inotify on this file system")
    g = w.generation()
    assert w.generation() == g == w.generation()  # quiet: the same number
    f.read_bytes()  # reading is no change
    assert w.generation() == g
    changes = [
        lambda: f.open("r+b").close(),  # opened for writing, nothing written: close_write
        lambda: os.truncate(f, 1024),
        lambda: f.open("r+b").write(b"x"),
        lambda: os.utime(f, (1, 1)),
        lambda: (tmp_path / "b").write_bytes(b"1"),
        lambda: os.replace(tmp_path / "b", f),
        lambda: f.unlink(),
    ]
    for change in changes:
        change()
        g2 = w.generation()
        assert g2 != g
        assert w.generation() == g2
        g = g2
    w.close()
    assert w.generation() is None and not w.active


def test_generation_also_changes_after_the_refresh_time(tmp_path, monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(watch.time, "monotonic", lambda: clock[0])
    w = watch.FolderWatch([tmp_path])
    if not w.active:
        pytest.skip("no inotify on this file system")
    g = w.generation()
    clock[0] += watch.REFRESH_S * 0.5
    assert w.generation() == g
    clock[0] += watch.REFRESH_S * 0.6
    assert w.generation() != g


def test_no_notice_on_network_file_systems(tmp_path, monkeypatch):
    monkeypatch.setattr(watch, "filesystem_type", lambda path, mountinfo=None: "nfs4")
    w = watch.FolderWatch([tmp_path])
    assert not w.active and w.generation() is None and w.current() is None


@pytest.fixture()
def small_map(tmp_path):
    rng = np.random.default_rng(0)
    pos = rng.normal((40.0, -3.7), 0.5, (200, 2))
    desc = rng.normal(size=(200, 32)).astype(np.float32)
    m = assemble_map(desc, pos, [f"r{i}" for i in range(200)],
                     {"name": "synthetic", "dim": 32, "config": {}, "preprocessing": {}}, {},
                     "kmeans", clusters=4)
    m.save(tmp_path / "m")
    return tmp_path / "m", desc


def _count_stats(monkeypatch) -> list[str]:
    seen: list[str] = []
    real = os.stat

    def counting(path, *a, **k):
        seen.append(os.fspath(path))
        return real(path, *a, **k)
    monkeypatch.setattr(store.os, "stat", counting)
    return seen


def test_a_quiet_map_is_not_statted_per_query_and_a_change_is_seen_by_the_next(
        small_map, monkeypatch):
    path, desc = small_map
    monkeypatch.setattr(watch, "REFRESH_S", 3600.0)
    loc = Localizer(ReferenceMap.load(path))
    if not loc.map.submaps[0].watch.active:
        pytest.skip("no inotify on this file system")
    for x in desc[:8]:
        loc.localize(x)  # every submap opened and its files checked once
    stats = _count_stats(monkeypatch)
    for x in desc[:8]:
        assert loc.localize(x).ref_id
    assert stats == []  # quiet: no stat at all
    best = loc.localize(desc[3]).candidates[0].submap
    sub = next(s for s in loc.map.submaps if s.id == best)
    rel = sub.files["coords"]
    with open(path / rel, "r+b") as fh:
        fh.truncate(os.path.getsize(path / rel) // 2)
    with pytest.raises(MapError, match="after the map was opened"):
        loc.localize(desc[3])  # the very next query
    assert stats  # it statted again


def test_a_refusal_starts_a_new_generation_for_the_maps_memo_of_passed_hits(small_map,
                                                                           monkeypatch):
    """The map remembers which submaps' hit files passed in the current generation; a
    submap refused in that generation (here: its coords rewritten through a shared mapping,
    which inotify does not report, and found by a check of all its files) bumps the
    generation, so the next query whose hits it holds fails instead of reading them."""
    import mmap

    path, desc = small_map
    monkeypatch.setattr(watch, "REFRESH_S", 3600.0)
    loc = Localizer(ReferenceMap.load(path))
    w = loc.map.submaps[0].watch
    if not w.active:
        pytest.skip("no inotify on this file system")
    for x in desc[:8]:
        loc.localize(x)
    best = loc.localize(desc[3]).candidates[0].submap
    si = next(i for i, s in enumerate(loc.map.submaps) if s.id == best)
    assert si in loc.map._hits_checked[1]  # passed in this generation: not checked again
    sub = loc.map.submaps[si]
    with open(path / sub.files["coords"], "r+b") as fh, mmap.mmap(fh.fileno(), 0) as mm:
        mm[-8:] = bytes(8) if mm[-8:] != bytes(8) else b"\x01" * 8  # no inotify event
    gen = w.current()
    with pytest.raises(MapError, match="refused"):
        sub.check_files()  # all roles: not passed in this generation, so statted
    assert w.generation() != gen
    with pytest.raises(MapError, match="refused"):
        loc.localize(desc[3])


def test_a_check_outside_a_query_drains_the_notice_itself(small_map, monkeypatch):
    path, desc = small_map
    monkeypatch.setattr(watch, "REFRESH_S", 3600.0)
    m = ReferenceMap.load(path)
    sub = m.submaps[0]
    sub.check_files()
    rel = sub.files["ids"]
    with open(path / rel, "r+b") as fh:
        fh.truncate(7)
    with pytest.raises(MapError, match=rel.split("/")[-1]):
        sub.check_files()


def test_without_notice_every_query_stats_as_before(small_map, monkeypatch):
    path, desc = small_map
    monkeypatch.setattr(watch, "LOCAL_FS", frozenset())
    loc = Localizer(ReferenceMap.load(path))
    assert loc.map.submaps[0].watch is not None and not loc.map.submaps[0].watch.active
    loc.localize(desc[1])
    stats = _count_stats(monkeypatch)
    loc.localize(desc[1])
    assert len(stats) >= 3  # the index searched, the hits' coords and ids


def test_a_forked_child_checks_every_time_and_leaves_the_events_to_its_parent(tmp_path,
                                                                          monkeypatch):
    monkeypatch.setattr(watch, "REFRESH_S", 3600.0)
    w = watch.FolderWatch([tmp_path])
    if not w.active:
        pytest.skip("no inotify on this file system")
    g = w.generation()
    (tmp_path / "x").write_bytes(b"1")
    monkeypatch.setattr(watch.os, "getpid", lambda: -1)  # as seen in a child
    assert w.generation() is None
    monkeypatch.undo()
    assert w.generation() != g  # the parent still sees the change
