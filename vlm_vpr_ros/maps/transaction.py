"""One edit of a map folder at a time, and its commit: files under new names, then the
manifest (``os.replace``, the commit point); a rollback deletes what the edit wrote.
See :mod:`vlm_vpr_ros.mapping.edit` for the generation scheme."""

from __future__ import annotations

import contextlib
import copy
import os
import time
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from vlm_vpr_ros import __version__
from vlm_vpr_ros.errors import MapError, OutputError
from vlm_vpr_ros.files.atomic import atomic_save_npy, atomic_write_index, atomic_write_json
from vlm_vpr_ros.files.lock import WriterLock, lock_path
from vlm_vpr_ros.maps import store
from vlm_vpr_ros.maps.format import MANIFEST, file_entry
from vlm_vpr_ros.maps.submap import Submap, submap_radius_km


@contextlib.contextmanager
def edit_lock(map_dir: Path, what: str = "a map edit") -> Iterator[None]:
    """Exclusive writer lock of a map folder for one edit: the lock every writer of the map
    takes (:class:`~vlm_vpr_ros.files.lock.WriterLock`, ``PARENT/.MAP.lock``; builds with and
    without ``--overwrite`` too). Waits a little, then MapError when another writer holds it."""
    if not (map_dir / MANIFEST).is_file():
        raise MapError(f"{map_dir} is not a map (no {MANIFEST})")
    # the entry (what a rebuild swaps) and, when it is a symbolic link, the folder it names
    # (what another edit through the real path writes into)
    targets = [Path(map_dir)]
    real = Path(os.path.realpath(map_dir))
    if lock_path(real) != lock_path(map_dir):
        targets.append(real)
    held: list[WriterLock] = []
    try:
        for k, t in enumerate(targets):  # one folder: its inside lock once
            held.append(WriterLock(t, what, inside_ok=k == 0).acquire())
    except OutputError as exc:
        for lock in held:
            lock.release()
        raise MapError(str(exc)) from None
    try:
        yield
    finally:
        for lock in reversed(held):
            lock.release()


def _folder_id(path: Path) -> tuple[int, int]:
    st = os.stat(path)
    return st.st_dev, st.st_ino


class Transaction:
    """Files written under new names, then the manifest; rollback deletes the new files."""

    def __init__(self, path: Path, manifest: dict) -> None:
        self.path = path
        self.old = manifest
        self.new = copy.deepcopy(manifest)
        self.written: list[str] = []
        #: files the manifest does not list (stored images) that this edit replaces
        self.retiring: list[str] = []
        #: the folder this edit opened: every write checks that ``path`` still names it
        self.folder = _folder_id(path)

    def check_folder(self) -> None:
        """MapError when ``path`` no longer names the folder this edit opened (it was moved or
        swapped by a process that did not take the writer lock): nothing is written through a
        path that now names another map."""
        try:
            same = _folder_id(self.path) == self.folder
        except OSError:
            same = False
        if not same:
            raise MapError(f"{self.path} was moved or replaced while this edit ran; the edit "
                           "is abandoned (nothing was committed): run it again")

    def retire(self, rel: str) -> None:
        """A file the manifest does not list (a stored image) that the committed map no longer
        uses: kept one generation like the replaced files, then deleted."""
        self.retiring.append(rel)

    def record(self, rel: str) -> None:
        self.written.append(rel)
        self.new["files"][rel] = file_entry(self.path, rel)

    def write_submap(self, sub: Submap, gen: int) -> dict:
        """Write a submap under generation-stamped names in the map's own format version;
        returns its manifest entry."""
        self.check_folder()
        entry = {"id": sub.id, "count": sub.count,
                 "centroid": [round(float(c), 7) for c in sub.centroid]}
        if int(self.old.get("version", 1)) >= 2:  # format v2 (vlm_vpr_ros.maps.store)
            kind = getattr(sub, "kind", "flat")
            rel = store.write_submap(self.path, f"{sub.id}.g{gen}", kind, sub.index, sub.coords,
                               list(sub.ids), getattr(sub, "rerank", None))
            entry.update({"group": getattr(sub, "group", "") or sub.id, "kind": kind,
                          "radius_km": round(submap_radius_km(sub), 4)})
            if getattr(sub, "recall", None):
                entry["recall"] = sub.recall
        else:
            stem = f"submaps/{sub.id}.g{gen}"
            rel = {"index": f"{stem}.faiss", "coords": f"{stem}.coords.npy",
                   "ids": f"{stem}.ids.json"}
            atomic_write_index(self.path / rel["index"], sub.index)
            atomic_save_npy(self.path / rel["coords"], np.asarray(sub.coords, np.float64))
            atomic_write_json(self.path / rel["ids"], list(sub.ids))
        for r in rel.values():
            self.record(r)
        entry["files"] = rel
        return entry

    def commit(self) -> None:
        """Replace the manifest (the commit point). The files the new manifest no longer lists
        are kept for one more generation (``retired``): a process that opened the previous
        generation lazily (format v2) can still open its submaps until it reloads; the files
        retired by the edit before are deleted now."""
        self.check_folder()
        listed = self.new["files"]
        for rel in list(listed):
            if not (self.path / rel).is_file():
                raise MapError(f"internal: {rel} listed but not written")
        keep = set(listed) | set(self.written)  # an image written again is not retired
        gone = sorted((set(self.old["files"]) - set(listed))
                      | {r for r in self.retiring if r not in keep})
        older = [r for r in self.old.get("retired", []) if r not in keep]
        self.new["retired"] = gone
        atomic_write_json(self.path / MANIFEST, self.new)
        for rel in older:
            with contextlib.suppress(FileNotFoundError):
                (self.path / rel).unlink()

    def rollback(self) -> None:
        try:
            self.check_folder()
        except MapError:
            return  # the folder at ``path`` is not ours any more: delete nothing there
        for rel in self.written:
            if rel not in self.old["files"]:
                with contextlib.suppress(FileNotFoundError):
                    (self.path / rel).unlink()


def finish_manifest(manifest: dict, entries: list[dict], gen: int, op: str, count: int,
                     source: Mapping[str, Any] | None) -> None:
    entries.sort(key=lambda e: e["id"])
    manifest["submaps"] = entries
    manifest["n_references"] = sum(int(e["count"]) for e in entries)
    manifest["n_submaps"] = len(entries)
    manifest["generation"] = gen
    manifest["software"] = f"vlm_vpr_ros {__version__}"
    src = manifest.setdefault("source", {})
    if src.get("fingerprint"):  # the map no longer equals what build-map would rebuild
        src["built_fingerprint"] = src.pop("fingerprint")
    src.setdefault("edits", []).append({
        "operation": op, "references": count, "generation": gen,
        "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **dict(source or {})})
