"""Two writers of one map (or one shard folder): one writer lock, no lost edit, no map deleted
under an edit; `describe` output safety (staged, never over a user's folder or an input)."""

from __future__ import annotations

import json
import os
import shutil
import threading

import numpy as np
import pytest

from faults.conftest import copy_refs, exit2, sha_tree

FAST = ("--descriptor", "vlad_rootsift_fast", "--partition", "none")


def _subset(tmp_path, demo_data, n, name="c.csv"):
    rows = (demo_data / "coords.csv").read_text().splitlines()
    p = tmp_path / name
    p.write_text("\n".join(rows[: n + 1]) + "\n")
    return p


@pytest.fixture
def new_refs(tmp_path, demo_data):
    """20 references the demo map does not hold (copies of demo images under new names)."""
    folder = tmp_path / "new"
    rows = [(f, a + 1e-4, b) for f, a, b in copy_refs(demo_data, folder, 20)]
    csv = tmp_path / "new.csv"
    csv.write_text("file,lat,lon\n" + "".join(f"{f},{a!r},{b!r}\n" for f, a, b in rows))
    return folder, csv, rows


class _Paused:
    """Run ``fn`` in a thread that stops inside ``owner.method`` until released."""

    def __init__(self, monkeypatch, owner, method: str, fn) -> None:
        self.inside, self.gate = threading.Event(), threading.Event()
        self.result, self.error = None, None
        real = getattr(owner, method)

        def paused(*a, **k):
            self.inside.set()
            assert self.gate.wait(120)
            return real(*a, **k)

        monkeypatch.setattr(owner, method, paused)
        self.thread = threading.Thread(target=self._run, args=(fn,), daemon=True)
        self.thread.start()
        assert self.inside.wait(120), self.error

    def _run(self, fn) -> None:
        try:
            self.result = fn()
        except BaseException as exc:  # noqa: BLE001 - reported by finish()
            self.error = exc

    def finish(self):
        self.gate.set()
        self.thread.join(120)
        return self.result, self.error


@pytest.mark.fault("lock_build_during_add")
def test_build_overwrite_while_map_add_runs(cli, map_copy, demo_data, tmp_path, new_refs,
                                            monkeypatch):
    from vlm_vpr_ros.mapping.edit import add_references
    from vlm_vpr_ros.maps.reference_map import ReferenceMap
    from vlm_vpr_ros.maps.transaction import Transaction

    folder, _, rows = new_refs
    monkeypatch.setenv("VLM_VPR_LOCK_WAIT_S", "0.3")
    add = _Paused(monkeypatch, Transaction, "commit",
                  lambda: add_references(map_copy, folder, rows, progress=False))
    coords = _subset(tmp_path, demo_data, 12)
    build = ("build-map", "--images", demo_data / "images", "--coords", coords, "--out",
             map_copy, "--overwrite", *FAST)
    exit2(cli(*build), "is being written by another process", "map add")
    assert not (tmp_path / ".map.partial").exists()
    res, err = add.finish()
    assert err is None and res.count == 20
    m = ReferenceMap.load(map_copy)  # the 20 added references are all there
    assert m.n_references == 91 and {f for f, _, _ in rows} <= set(m.all_ids())
    # a writer that may wait long enough gets the lock once the edit is done
    monkeypatch.setenv("VLM_VPR_LOCK_WAIT_S", "30")
    assert cli(*build)[0] == 0 and ReferenceMap.load(map_copy).n_references == 12
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["c.csv", "map", "new", "new.csv"])  # no lock file, no staging folder left


@pytest.mark.fault("lock_add_during_build")
def test_map_add_while_build_overwrite_runs(cli, map_copy, demo_data, tmp_path, new_refs,
                                            monkeypatch):
    from vlm_vpr_ros.files.outputs import StagedOutput
    from vlm_vpr_ros.mapping.build_images import build_map
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    folder, csv, _ = new_refs
    monkeypatch.setenv("VLM_VPR_LOCK_WAIT_S", "0.3")
    coords = _subset(tmp_path, demo_data, 12)
    build = _Paused(monkeypatch, StagedOutput, "commit", lambda: build_map(
        demo_data / "images", coords, map_copy, descriptor="vlad_rootsift_fast",
        partition="none", overwrite=True, progress=False))
    before = sha_tree(map_copy)
    exit2(cli("map", "add", map_copy, "--images", folder, "--coords", csv),
          "is being written by another process")
    (tmp_path / "ids.txt").write_text("new_0.jpg\n")
    exit2(cli("map", "remove", map_copy, "--ids", tmp_path / "ids.txt"),
          "is being written by another process")
    assert sha_tree(map_copy) == before  # the edits wrote nothing into the old map
    _, err = build.finish()
    assert err is None
    m = ReferenceMap.load(map_copy, verify=True)  # the rebuilt map is whole and loads
    assert m.n_references == 12 and not any(i.startswith("new_") for i in m.all_ids())


@pytest.mark.fault("lock_edit_folder_swapped")
def test_edit_never_writes_through_a_swapped_path(map_copy, tmp_path, new_refs, monkeypatch):
    """A tool that ignores the lock (`mv`, `rsync`) swaps the map while an edit runs: the edit
    is abandoned; nothing is written into the folder now at that path."""
    from vlm_vpr_ros.errors import MapError
    from vlm_vpr_ros.mapping.edit import add_references
    from vlm_vpr_ros.maps.reference_map import ReferenceMap
    from vlm_vpr_ros.maps.transaction import Transaction

    folder, _, rows = new_refs
    add = _Paused(monkeypatch, Transaction, "commit",
                  lambda: add_references(map_copy, folder, rows, progress=False))
    old = tmp_path / "moved"
    map_copy.rename(old)
    shutil.copytree(old, map_copy)
    shutil.rmtree(map_copy / "submaps")
    shutil.copytree(old / "submaps", map_copy / "submaps",
                    ignore=lambda d, names: [n for n in names if ".g1." in n])
    before = sha_tree(map_copy)
    _, err = add.finish()
    assert isinstance(err, MapError) and "moved or replaced while this edit ran" in str(err)
    assert sha_tree(map_copy) == before
    assert ReferenceMap.load(map_copy).n_references == 71
    assert ReferenceMap.load(old).n_references == 71  # its manifest was never replaced


# -- describe -------------------------------------------------------------------------------------
def _describe(cli, images, coords, out, *extra):
    return cli("describe", "--images", images, "--coords", coords, "--out", out,
               "--descriptor", "vlad_rootsift_fast", "--shard-size", "4", *extra)


@pytest.mark.fault("out_describe_not_ours")
def test_describe_overwrite_refuses_a_user_folder(cli, demo_data, tmp_path):
    docs = tmp_path / "docs"
    docs.mkdir()
    for name in ("shard_000000000.npy", "describe.json", "descriptor_state.npz", "notes.txt"):
        (docs / name).write_text("the user's own file")
    coords = _subset(tmp_path, demo_data, 6)
    before = sha_tree(docs)
    for extra in ((), ("--overwrite",)):
        msg = exit2(_describe(cli, demo_data / "images", coords, docs, *extra),
                    "left untouched")
        assert "--overwrite" not in msg.replace(str(docs), "DIR")
        assert sha_tree(docs) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv", "docs"]


@pytest.mark.fault("out_describe_into_images")
def test_describe_out_is_the_images_folder(cli, demo_data, tmp_path):
    images = tmp_path / "images"
    shutil.copytree(demo_data / "images", images)
    coords = _subset(tmp_path, demo_data, 6)
    before = sha_tree(images)
    for out in (images, images / "shards", tmp_path):
        exit2(_describe(cli, images, coords, out, "--overwrite"), "never written into inputs")
        assert sha_tree(images) == before


@pytest.mark.fault("out_describe_staged")
def test_describe_is_staged_and_replaces_only_its_own(cli, demo_data, tmp_path, monkeypatch):
    from vlm_vpr_ros.distributed import describe as describe_mod

    out = tmp_path / "s"
    first = _subset(tmp_path, demo_data, 6)
    assert _describe(cli, demo_data / "images", first, out)[0] == 0
    meta = json.loads((out / "describe.json").read_text())
    assert meta["described"] == 6 and (out / ".vlm_vpr_output.json").is_file()
    rc, stdout, _ = _describe(cli, demo_data / "images", first, out)
    assert rc == 0 and "up to date" in cli.text  # the same job: nothing recomputed
    other = _subset(tmp_path, demo_data, 9, "c9.csv")
    exit2(_describe(cli, demo_data / "images", other, out), "pass --overwrite")
    before = sha_tree(out)
    real = describe_mod._run

    def fails(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(describe_mod, "_run", fails)  # interrupted: the old folder stays
    assert _describe(cli, demo_data / "images", other, out, "--overwrite")[0] == 130
    assert sha_tree(out) == before
    monkeypatch.setattr(describe_mod, "_run", real)
    assert _describe(cli, demo_data / "images", other, out, "--overwrite")[0] == 0
    assert json.loads((out / "describe.json").read_text())["described"] == 9
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv", "c9.csv", "s"]


# -- the lock itself, and every writer takes it -----------------------------------------------
@pytest.mark.fault("lock_stale_file")
def test_lock_file_left_by_kill9_is_taken_over(cli, map_copy, tmp_path, new_refs):
    """A writer killed with -9 leaves PARENT/.MAP.lock behind, unlocked (the kernel released
    the flock): the next writer takes it over and deletes it when done."""
    folder, csv, _ = new_refs
    (tmp_path / ".map.lock").write_text("pid 999999, map add, since yesterday\n")
    rc, out, _ = cli("map", "add", map_copy, "--images", folder, "--coords", csv)
    assert rc == 0 and "20 references added" in out
    assert not (tmp_path / ".map.lock").exists()


@pytest.mark.fault("lock_wait_env_bad")
def test_lock_wait_setting_checked(cli, map_copy, tmp_path, monkeypatch):
    (tmp_path / "ids.txt").write_text("x\n")
    for bad in ("abc", "-1", "inf", "nan"):
        monkeypatch.setenv("VLM_VPR_LOCK_WAIT_S", bad)
        exit2(cli("map", "remove", map_copy, "--ids", tmp_path / "ids.txt"),
              "VLM_VPR_LOCK_WAIT_S")


@pytest.fixture
def held(monkeypatch):
    """Hold a target's writer lock (as another process would) and refuse at once."""
    from vlm_vpr_ros.files.lock import WriterLock

    monkeypatch.setenv("VLM_VPR_LOCK_WAIT_S", "0")
    locks = []

    def hold(target, what="another writer"):
        locks.append(WriterLock(target, what).acquire())

    yield hold
    for lock in locks:
        lock.release()


@pytest.mark.fault("lock_every_writer")
def test_every_map_writer_takes_the_lock(cli, map_copy, tmp_path, demo_data, held):
    """build-map (images, descriptors, --bag), map add/remove/upgrade and calibrate on a map
    whose lock is held: each is refused before writing anything."""
    held(map_copy, "map add")
    before = sha_tree(map_copy)
    coords = _subset(tmp_path, demo_data, 4)
    np.save(tmp_path / "d.npy", np.ones((4, 512), np.float32))
    (tmp_path / "ids.txt").write_text("x\n")
    (tmp_path / "r.csv").write_text("file,lat,lon,uncertainty_m,radius95_m\n")
    for args in (
            ("build-map", "--images", demo_data / "images", "--coords", coords, "--out",
             map_copy, "--overwrite", *FAST),
            ("build-map", "--descriptors", tmp_path / "d.npy", "--coords", coords, "--out",
             map_copy, "--descriptor", "cosplace", "--overwrite"),
            ("build-map", "--bag", tmp_path / "nobag", "--out", map_copy, "--overwrite"),
            ("map", "remove", map_copy, "--ids", tmp_path / "ids.txt"),
            ("map", "upgrade", map_copy, "--out", tmp_path / "v2"),
            ("calibrate", "--map", map_copy, "--results", tmp_path / "r.csv",
             "--ground-truth", coords)):
        exit2(cli(*args), "is being written by another process", "map add")
    assert sha_tree(map_copy) == before and not (tmp_path / "v2").exists()


@pytest.mark.fault("lock_other_outputs")
def test_describe_and_bag_make_take_the_lock(cli, tmp_path, demo_data, held):
    coords = _subset(tmp_path, demo_data, 3)
    held(tmp_path / "s", "describe")
    exit2(_describe(cli, demo_data / "images", coords, tmp_path / "s"),
          "being written by another process", "describe")
    held(tmp_path / "bag", "bag make")
    exit2(cli("bag", "make", "--images", demo_data / "images", "--coords", coords, "--out",
              tmp_path / "bag"), "being written by another process", "bag make")
    assert sorted(p.name for p in tmp_path.iterdir()) == [".bag.lock", ".s.lock", "c.csv"]


@pytest.mark.fault("out_upgrade_into_map")
def test_upgrade_out_inside_the_source(cli, map_copy):
    before = sha_tree(map_copy)
    exit2(cli("map", "upgrade", map_copy, "--out", map_copy / "v2"),
          "never written into inputs")
    assert sha_tree(map_copy) == before


@pytest.mark.fault("lock_symlinked_map")
def test_edit_through_a_symlink_and_the_real_path(cli, map_copy, tmp_path, held):
    """`map add maps/city` (a link to the real folder) and an edit of the real folder exclude
    each other; a rebuild of the link's entry and an edit through the link too."""
    (tmp_path / "maps").mkdir()
    link = tmp_path / "maps" / "city"
    link.symlink_to(map_copy)
    (tmp_path / "ids.txt").write_text("x\n")
    held(map_copy, "map add")  # an edit through the real path
    exit2(cli("map", "remove", link, "--ids", tmp_path / "ids.txt"), "map add")
    held(link, "a map build")  # a rebuild of maps/city
    exit2(cli("map", "remove", link, "--ids", tmp_path / "ids.txt"), "a map build")


@pytest.mark.fault("out_describe_resume_adopt")
def test_describe_resumes_an_unfinished_folder_written_in_place(cli, demo_data, tmp_path,
                                                                 monkeypatch):
    """A shard folder left unfinished by a version that wrote in place is adopted and resumed
    (finished shards are not recomputed), then swapped in."""
    from vlm_vpr_ros.distributed import describe as describe_mod

    coords = _subset(tmp_path, demo_data, 9)
    out = tmp_path / "s"
    real, calls = describe_mod._run, []

    def stop_after_first(engine, store, ids, pending, *a, **k):
        calls.append(len(pending))
        if len(calls) == 1:  # write one shard, then "crash"
            real(engine, store, ids, pending[:1], *a, **k)
            raise KeyboardInterrupt
        return real(engine, store, ids, pending, *a, **k)

    monkeypatch.setattr(describe_mod, "_run", stop_after_first)
    assert _describe(cli, demo_data / "images", coords, out)[0] == 130
    staged = tmp_path / ".s.partial" / "s"
    staged.rename(out)  # what an older version left: the unfinished job at --out itself
    shutil.rmtree(tmp_path / ".s.partial")
    rc, stdout, _ = _describe(cli, demo_data / "images", coords, out)
    assert rc == 0 and "1 shards resumed" in stdout and calls == [3, 2]
    assert json.loads((out / "describe.json").read_text())["described"] == 9


def _old_map(tmp_path):
    target = tmp_path / "m6"
    target.mkdir()
    (target / "manifest.json").write_text('{"format": "vlm_vpr_ros.map", "old": true}')
    return target


def _stage_new(target):
    from vlm_vpr_ros.files.outputs import StagedOutput

    with StagedOutput(target, "map", overwrite=True) as st:
        (st.path / "manifest.json").write_text('{"format": "vlm_vpr_ros.map", "new": true}')
        st.commit()


@pytest.mark.fault("out_old_cleanup_interrupted")
def test_overwrite_after_an_interrupted_cleanup_of_the_old_output(tmp_path):
    """Ctrl-C while the replaced output was being deleted (after the swap): a half-deleted
    `.NAME.partial/.old` is left; the next `--overwrite` removes it and succeeds."""
    target = _old_map(tmp_path)
    half = tmp_path / ".m6.partial" / ".old" / "submaps"
    half.mkdir(parents=True)
    (half / "k000.faiss").write_bytes(b"x" * 10)
    _stage_new(target)  # before the fix: "cannot write m6: Directory not empty", forever
    assert json.loads((target / "manifest.json").read_text()) == {
        "format": "vlm_vpr_ros.map", "new": True}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m6"]


@pytest.mark.fault("out_swap_interrupted")
def test_ctrl_c_between_the_two_renames_keeps_the_old_output(tmp_path, monkeypatch):
    """Ctrl-C right after the old output was moved aside, before the new one is moved in:
    the old output is put back (not deleted with the staging folder)."""
    import os

    target = _old_map(tmp_path)
    before = sha_tree(target)
    real = os.replace

    def interrupted(src, dst):
        real(src, dst)
        if str(dst).endswith(".old"):
            raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _stage_new(target)
    monkeypatch.setattr(os, "replace", real)
    assert sha_tree(target) == before  # before the fix: m6 gone with .m6.partial
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m6"]
    _stage_new(target)
    assert json.loads((target / "manifest.json").read_text())["new"] is True


def _no_write(monkeypatch, lockfile):
    """This process may read ``lockfile`` but not write or create it (another user's lock
    file, or a parent folder read-only for us: root ignores permission bits, so simulated)."""
    import errno
    import os

    from vlm_vpr_ros.files import lock

    def guarded(path, flags, *a, **k):
        if str(path) == str(lockfile) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return os.open(path, flags, *a, **k)

    monkeypatch.setattr(lock, "_sys_open", guarded)


@pytest.mark.fault("lock_file_not_writable")
def test_edit_waits_on_another_users_lock_file(map_copy, monkeypatch, held):
    """Another user's edit holds `PARENT/.MAP.lock`, which this user can read but not write:
    this user's edit takes the same lock (read-only) and is refused, never a second lock."""
    from vlm_vpr_ros.errors import MapError
    from vlm_vpr_ros.maps.transaction import edit_lock

    held(map_copy, "map add")  # the other user
    _no_write(monkeypatch, map_copy.parent / ".map.lock")
    with pytest.raises(MapError, match=r"being written by another process \(pid .*map add"):
        with edit_lock(map_copy, "map remove"):  # before the fix: took MAP/.edit.lock
            pass


@pytest.mark.fault("lock_parent_not_writable")
def test_edit_without_the_lock_beside_the_map_excludes_the_others(map_copy, monkeypatch):
    """A user who cannot create `PARENT/.MAP.lock` edits under `MAP/.edit.lock` only; another
    user's edit and rebuild of that map wait for it too (they take both locks)."""
    from vlm_vpr_ros.errors import MapError, OutputError
    from vlm_vpr_ros.files.lock import WriterLock
    from vlm_vpr_ros.files.outputs import StagedOutput
    from vlm_vpr_ros.maps.transaction import edit_lock

    monkeypatch.setenv("VLM_VPR_LOCK_WAIT_S", "0")
    _no_write(monkeypatch, map_copy.parent / ".map.lock")
    mine = WriterLock(map_copy, "map add", inside_ok=True).acquire()
    assert mine.path == map_copy / ".edit.lock"
    from vlm_vpr_ros.files import lock

    monkeypatch.setattr(lock, "_sys_open", os.open)  # the other user may write the parent
    before = {k: v for k, v in sha_tree(map_copy).items() if not k.endswith(".edit.lock")}
    try:
        with pytest.raises(MapError, match="being written by another process"):
            with edit_lock(map_copy, "map remove"):  # before the fix: both edits ran
                pass
        with pytest.raises(OutputError, match="being written by another process"):
            with StagedOutput(map_copy, "map", overwrite=True) as st:
                shutil.copytree(map_copy, st.path, dirs_exist_ok=True)
                st.commit()  # the swap waits for the edit
    finally:
        mine.release()
    assert sha_tree(map_copy) == before and not (map_copy / ".edit.lock").exists()
    with edit_lock(map_copy, "map remove"):  # free again
        pass
