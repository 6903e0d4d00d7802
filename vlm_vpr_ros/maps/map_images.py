"""Reference images kept inside a map (teach maps built from a bag): ``MAP/images/<id>``,
listed with size and sha256 in ``MAP/images/index.g<generation>.json`` (itself in the
manifest's ``files``). Adding to such a map copies the new images in; removing deletes them.

Maps built from a folder of images (``build-map --images DIR``) keep no pictures but record
where they came from: the manifest's ``source_images`` names the folder (absolute) and
``source_images.npy`` beside the manifest (listed in ``files``) the size and sha256 of every
picture as the build read it. :class:`SourceImages` reads a picture from there (or from the
folder a user names instead) only when its bytes are still those: a changed or missing picture
is skipped with one WARN naming it, never shown in place of the one the map was built from.
The record follows the map's edits (:func:`edit_source_index`): a removed reference leaves it,
and a reference added under a removed one's name is never vouched for by the old record."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.errors import DataError, MapError
from vlm_vpr_ros.files.atomic import (atomic_path, atomic_save_npy, atomic_write_json,
                                      file_sha256)
from vlm_vpr_ros.files.images import MAX_FILE_BYTES
from vlm_vpr_ros.maps.format import (MANIFEST, bad_ref_id, check_content, checked_file,
                                     file_table)
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.maps.transaction import Transaction, edit_lock

log = logging.getLogger(__name__)
IMAGES_DIR = "images"
#: the index of the pictures a map was built from (beside the manifest, listed in ``files``)
SOURCE_INDEX = "source_images.npy"
_warned: set[tuple[str, ...]] = set()  # one WARN per (map, folder or picture, what)


def _warn_once(key: tuple[str, ...], msg: str, *args: Any) -> None:
    if key not in _warned:
        _warned.add(key)
        log.warning(msg, *args)


def images_folder(map_dir: str | os.PathLike[str] | None, manifest: Mapping[str, Any],
                  override: str | os.PathLike[str] = "", source: bool = False) -> Path | None:
    """Where a map's reference images are: ``override`` when given (the node's
    ``reference_images_dir``, ``--reference-images``: the folder the map was built from), else
    the map's own images folder (teach maps keep their pictures), else, with ``source``, the
    folder a ``build-map --images`` map was built from while it exists (:func:`source_folder`),
    else None. Verification of maps without stored features, ``--save-matches`` and the node's
    debug view all look here; ``source`` is for readers that check every picture against the
    build's index (:class:`SourceImages`: the debug view)."""
    if override:
        return Path(override).expanduser()
    entry = manifest.get("images") or {}
    if map_dir is not None and entry:
        return Path(map_dir) / entry.get("folder", IMAGES_DIR)
    if source:
        return source_folder(map_dir, manifest)
    return None


def _source_entry(map_dir: str | os.PathLike[str] | None,
                  manifest: Mapping[str, Any]) -> dict | None:
    """The manifest's ``source_images`` entry when it is well formed (else one WARN, None)."""
    entry = manifest.get("source_images")
    if entry is None:
        return None
    ok = (isinstance(entry, dict) and isinstance(entry.get("folder"), str)
          and Path(entry["folder"]).is_absolute() and isinstance(entry.get("index"), str)
          and entry["index"] in (manifest.get("files") or {}))
    if not ok:
        _warn_once((str(map_dir), "entry"), "%s: manifest field 'source_images' is malformed "
                   "(expected {folder: absolute path, index: a file listed in 'files'}): the "
                   "folder the map was built from is not used", map_dir)
        return None
    return entry


def source_folder(map_dir: str | os.PathLike[str] | None,
                  manifest: Mapping[str, Any]) -> Path | None:
    """The folder a ``build-map --images`` map was built from, None when the map records none
    or when it is gone (one WARN: moved or deleted)."""
    entry = _source_entry(map_dir, manifest)
    if entry is None:
        return None
    folder = Path(entry["folder"])
    if not folder.is_dir():
        _warn_once((str(map_dir), entry["folder"], "gone"),
                   "%s: the map was built from the images in %s, which is no longer there "
                   "(moved or deleted): no reference pictures; set reference_images_dir "
                   "(--reference-images) to where they are now", map_dir, folder)
        return None
    return folder


def record_source_images(map_dir: str | os.PathLike[str], folder: str | os.PathLike[str],
                         ids: Sequence[str]) -> dict:
    """Record in a saved map the folder its pictures ``ids`` were read from (absolute) and the
    size and sha256 of each (:data:`SOURCE_INDEX`: rows ``id, bytes, sha256`` sorted by id, a
    ``.npy`` that is memory-mapped and binary-searched, so a planet-scale map does not load it;
    listed in ``files``); the manifest is replaced last. Returns the new manifest (used by
    ``build-map --images``)."""
    path, folder = Path(map_dir), Path(folder).expanduser().absolute()
    table = _index_table(_digest_rows(folder, sorted(set(ids)), path))
    manifest = json.loads((path / MANIFEST).read_text(encoding="utf-8"))
    atomic_save_npy(path / SOURCE_INDEX, table)
    manifest["files"].update(file_table(path, [SOURCE_INDEX]))
    manifest["source_images"] = {"folder": str(folder), "index": SOURCE_INDEX,
                                 "count": len(table), "check": "bytes+sha256"}
    atomic_write_json(path / MANIFEST, manifest)
    return manifest


def _digest_rows(folder: Path, ids: Sequence[str], label: Path) -> list[tuple]:
    """``(id, bytes, sha256)`` rows of the pictures ``ids`` in ``folder`` as they are now."""
    rows = []
    for ref_id in ids:
        p = folder / safe_rel(ref_id)
        try:
            with open(p, "rb") as fh:
                digest = hashlib.file_digest(fh, "sha256").digest()
                rows.append((ref_id.encode("utf-8"), os.fstat(fh.fileno()).st_size,
                             np.frombuffer(digest, np.uint8)))
        except OSError as exc:  # gone since the build (or the edit) read it: never shown
            log.warning("%s: reference %s is not recorded (%s)", label, ref_id, exc)
    return rows


def _index_table(rows: Sequence[tuple]) -> np.ndarray:
    """The :data:`SOURCE_INDEX` table of ``rows``, sorted by id (binary-searched)."""
    width = max([len(r[0]) for r in rows] + [1])
    table = np.array(list(rows), dtype=[("id", f"S{width}"), ("bytes", "<i8"),
                                        ("sha256", "u1", (32,))])
    return np.sort(table, order="id") if len(table) else table


def _same_folder(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(os.path.abspath(a)) == Path(os.path.abspath(b))


def edit_source_index(tx: Transaction, gen: int, removed: Sequence[str] = (),
                      added: Sequence[str] = (), added_from: Path | None = None) -> None:
    """Make the build's picture record follow a map edit (``map add`` / ``map remove``): a
    removed reference leaves the record, and so does every added one (a new picture under an
    old name must never pass the old picture's size and sha256), except references added
    from the recorded folder itself, which are recorded as they are now. References added
    from another folder are then not in the record: :class:`SourceImages` shows no picture for
    them (one WARN), never the build folder's picture of the same name. Written under a new,
    generation-stamped name like every file an edit writes."""
    entry = _source_entry(tx.path, tx.old)
    if entry is None or not (removed or added):
        return
    try:
        old = SourceIndex.open(tx.path, tx.old, entry["index"]).table
    except MapError as exc:  # an unusable record shows nothing anyway; the edit goes on
        log.warning("%s: the index of the pictures the map was built from is unusable (%s); "
                    "left as it is", tx.path, exc)
        return
    out = {r["id"].decode("utf-8"): (r["id"], int(r["bytes"]), np.asarray(r["sha256"]))
           for r in old}
    for ref_id in (*removed, *added):
        out.pop(ref_id, None)
    if added and added_from is not None and _same_folder(added_from, Path(entry["folder"])):
        out.update((r[0].decode("utf-8"), r) for r in _digest_rows(added_from, added, tx.path))
    table = _index_table([(k.encode("utf-8"), b, d) for k, (_, b, d) in out.items()])
    rel = f"source_images.g{gen}.npy"
    atomic_save_npy(tx.path / rel, table)
    tx.new["files"].pop(entry["index"], None)
    tx.record(rel)
    tx.new["source_images"] = {**entry, "index": rel, "count": len(table),
                               "generation": gen}


class SourceIndex:
    """The size and sha256 the build recorded per picture (:func:`record_source_images`),
    memory-mapped: a lookup reads a few pages."""

    def __init__(self, table: np.ndarray) -> None:
        if table.dtype.names != ("id", "bytes", "sha256") or table.ndim != 1:
            raise MapError(f"not an image index (fields {table.dtype.names})")
        self.table, self.width = table, table.dtype["id"].itemsize

    @classmethod
    def open(cls, map_dir: Path, manifest: Mapping[str, Any], rel: str) -> "SourceIndex":
        """The index the manifest lists, after the cheap content check of every map file."""
        p = checked_file(map_dir, manifest, rel, False)
        check_content(map_dir, manifest, [rel])
        try:
            return cls(np.load(p, mmap_mode="r", allow_pickle=False))
        except (OSError, ValueError) as exc:
            raise MapError(f"{p}: unreadable image index ({exc})") from None

    def get(self, ref_id: str) -> tuple[int, bytes] | None:
        """(bytes, sha256 digest) recorded for ``ref_id``; None when it is not listed."""
        key = ref_id.encode("utf-8")
        if len(key) > self.width:
            return None
        ids = self.table["id"]
        i = int(np.searchsorted(ids, key))
        if i >= len(ids) or ids[i] != key:
            return None
        row = self.table[i]
        return int(row["bytes"]), np.asarray(row["sha256"], np.uint8).tobytes()


class SourceImages:
    """The reference pictures of a map as bytes, by reference id: from ``folder``, each checked
    against the build's :class:`SourceIndex` when the map has one (opened at the first read).
    A picture that is missing, not listed, or whose bytes differ is None, with one WARN naming
    it."""

    def __init__(self, folder: str | os.PathLike[str] | None,
                 index: Callable[[], SourceIndex] | None = None, label: str = "") -> None:
        self.folder = Path(folder).expanduser() if folder else None
        self._open_index, self._index, self.label = index, None, label

    @classmethod
    def for_map(cls, map_dir: str | os.PathLike[str] | None, manifest: Mapping[str, Any],
                override: str | os.PathLike[str] = "") -> "SourceImages":
        """The folder of :func:`images_folder` (``source`` included). A map built from images
        checks its pictures against the build's index wherever they are read from (its
        recorded folder or ``override``); a teach map's own folder and old maps are read as
        they are (the map's files are checked by ``map verify``)."""
        folder = images_folder(map_dir, manifest, override, source=True)
        own = not override and bool(manifest.get("images"))
        entry = None if own else _source_entry(map_dir, manifest)
        if entry is None or folder is None or map_dir is None:
            return cls(folder, None, str(map_dir or ""))
        return cls(folder, lambda: SourceIndex.open(Path(map_dir), manifest, entry["index"]),
                   str(map_dir))

    def _lookup(self, ref_id: str) -> tuple[int, bytes] | None | bool:
        """The recorded (bytes, sha256) of ``ref_id``, None when unlisted, False when the index
        is unusable (one WARN: no picture is shown)."""
        if self._index is None:
            try:
                self._index = self._open_index()
            except MapError as exc:
                _warn_once((self.label, "index"), "%s: the index of the pictures the map was "
                           "built from is unusable (%s): no reference pictures", self.label, exc)
                self._index = False
        return self._index.get(ref_id) if self._index is not False else False

    def read(self, ref_id: str) -> bytes | None:
        """The picture's bytes, or None (missing, outside the folder, changed since the
        build)."""
        if self.folder is None or not ref_id or bad_ref_id(ref_id):
            return None
        checked = self._open_index is not None
        meta = self._lookup(ref_id) if checked else None
        if meta is False:
            return None
        p = self.folder / ref_id
        try:
            size = p.stat().st_size
            changed = meta is not None and size != meta[0]
            data = b"" if changed or size > MAX_FILE_BYTES else p.read_bytes()
        except OSError as exc:
            if checked:
                self._warn(p, "missing", f"is missing ({exc.strerror or exc})")
            else:
                log.debug("reference image %s not available: %s", ref_id, exc)
            return None
        if not checked:
            return data or None
        if meta is None:
            self._warn(p, "unlisted", "is not in the index of the pictures the map was built "
                       "from")
            return None
        if changed or len(data) != meta[0] or hashlib.sha256(data).digest() != meta[1]:
            self._warn(p, "changed", "changed since the map was built (size or sha256 differ)")
            return None
        return data

    def _warn(self, p: Path, kind: str, what: str) -> None:
        _warn_once((self.label, str(p), kind), "%s: reference picture %s %s: not shown",
                   self.label, p, what)


def pictures_problem(map_dir: str | os.PathLike[str], manifest: Mapping[str, Any],
                     ids: Sequence[str], override: str | os.PathLike[str] = "",
                     sample: int = 8) -> str:
    """Why the reference pictures of a map cannot be read ("" when they can): the check a
    calibration under reduced query conditions makes before it replaces the one it has (a
    calibration without pictures would silently cover full-size queries only). The folder of
    :meth:`SourceImages.for_map` must exist and at least one of ``sample`` pictures spread over
    ``ids`` must read and pass the build's record."""
    pictures = SourceImages.for_map(map_dir, manifest, override)
    recorded = None if override or manifest.get("images") else _source_entry(map_dir, manifest)
    folder = pictures.folder or (Path(recorded["folder"]) if recorded else None)
    if folder is None:
        return ("the map holds no pictures and records no folder it was built from "
                "(--reference-images DIR)")
    if not folder.is_dir():
        return (f"the picture folder {folder} is not there (moved or deleted? "
                "--reference-images DIR)")
    if not ids:
        return ""
    step = max(1, len(ids) // max(1, sample))
    tried = list(ids[::step][:sample])
    if any(pictures.read(i) is not None for i in tried):
        return ""
    return (f"none of {len(tried)} pictures tried (e.g. {tried[0]}) reads from "
            f"{pictures.folder} as the map recorded it (--reference-images DIR)")


def image_index(map_dir: Path, manifest: Mapping[str, Any]) -> dict[str, dict]:
    """``{id: {"bytes", "sha256"}}`` of the images a map holds ({} when it holds none)."""
    entry = manifest.get("images")
    if not entry:
        return {}
    if entry["index"] in manifest.get("files", {}):  # checked like every file the map lists
        p = checked_file(Path(map_dir), manifest, entry["index"], True)
    else:
        p = map_dir / entry["index"]
    try:
        return dict(json.loads(p.read_text(encoding="utf-8")))
    except (OSError, ValueError, TypeError) as exc:
        raise MapError(f"{map_dir}: cannot read the image index {entry['index']}: {exc}") from exc


def safe_rel(ref_id: str) -> Path:
    """``ref_id`` as a path inside the images folder (the rules of every stored id)."""
    if bad_ref_id(ref_id):
        raise DataError(f"reference id {ref_id!r} is not a relative path inside the images "
                        "folder; it cannot be stored in the map")
    return Path(ref_id)


def store_images(tx: Transaction, src_root: Path, ids: Sequence[str], index: dict,
                  gen: int, move: bool = False) -> None:
    for ref_id in ids:
        dst = tx.path / IMAGES_DIR / safe_rel(ref_id)
        dst.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(dst) as tmp:
            if move:
                os.replace(src_root / ref_id, tmp)
            else:
                shutil.copyfile(src_root / ref_id, tmp)
        tx.written.append(f"{IMAGES_DIR}/{ref_id}")
        index[ref_id] = {"bytes": dst.stat().st_size, "sha256": file_sha256(dst)}
    write_image_index(tx, index, gen)


def write_image_index(tx: Transaction, index: dict, gen: int) -> None:
    old = tx.old.get("images")
    if old:
        tx.new["files"].pop(old["index"], None)
    if not index:
        tx.new.pop("images", None)
        return
    rel = f"{IMAGES_DIR}/index.g{gen}.json"
    atomic_write_json(tx.path / rel, dict(sorted(index.items())))
    tx.record(rel)
    tx.new["images"] = {"folder": IMAGES_DIR, "index": rel, "count": len(index)}


def attach_images(map_dir: str | os.PathLike[str], images_dir: str | os.PathLike[str],
                  ids: Sequence[str] | None = None) -> None:
    """Move the reference images of a freshly built map (``images_dir/<id>``) into it and list
    them in its manifest (used by ``build-map --bag``)."""
    path = Path(map_dir)
    with edit_lock(path, "storing the images of a teach map"):
        manifest = json.loads((path / MANIFEST).read_text(encoding="utf-8"))
        ref_ids = ids if ids is not None else ReferenceMap.load(path, verify=False).all_ids()
        tx = Transaction(path, manifest)
        src = tx.new.pop("source_images", None)  # the build's scratch folder: not kept
        if isinstance(src, dict):
            tx.new["files"].pop(src.get("index"), None)
        try:
            store_images(tx, Path(images_dir), list(ref_ids), image_index(path, manifest),
                          int(manifest.get("generation", 0)), move=True)
            tx.commit()
        except BaseException:
            tx.rollback()
            raise


def verify_images(map_dir: str | os.PathLike[str]) -> int:
    """Check every image a map holds against its index (size, sha256); returns the count."""
    path = Path(map_dir)
    manifest = json.loads((path / MANIFEST).read_text(encoding="utf-8"))
    index = image_index(path, manifest)
    for ref_id, meta in index.items():
        p = path / IMAGES_DIR / ref_id
        if not p.is_file():
            raise MapError(f"{path}: image {ref_id} is listed but missing")
        if p.stat().st_size != meta["bytes"] or file_sha256(p) != meta["sha256"]:
            raise MapError(f"{path}: image {ref_id} does not match its checksum")
    return len(index)
