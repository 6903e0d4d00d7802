"""Map format v2 on disk: memory-mapped arrays, submaps opened lazily, sizes checked at start.

Layout (``manifest.json`` is written last; every file is written to a temporary name and moved
into place, so a folder with a manifest is complete)::

    MAP/manifest.json            version 2: descriptor identity, partition, index kinds, submaps
                                 (id, group, count, centroid, kind, measured recall, files),
                                 bytes + sha256 of every file
    MAP/descriptor_state.npz     fitted descriptor state, if any (no pickle)
    MAP/submaps/<id>.faiss       flat / fp16: read memory-mapped; pq: fast-scan codes (in RAM)
    MAP/submaps/<id>.f16.npy     pq only: (n, dim) float16 re-rank vectors (memory-mapped)
    MAP/submaps/<id>.coords.npy  (n, 2) float64 lat/lon (memory-mapped)
    MAP/submaps/<id>.ids.npy     (n,) fixed-width UTF-8 bytes ``S<w>`` (memory-mapped)

Opening a map reads the manifest, ``stat``s every file (sizes must match) and checks every
file's content fingerprint (:func:`~vlm_vpr_ros.maps.format.check_content`: small files whole,
large ones by sampled pages), so files swapped between submaps or rewritten with the same size
are refused. A submap is opened on first use (sizes checked again before mapping). A file
truncated while the map is open would make the next page access raise SIGBUS (a crash Python
cannot catch), so every search first ``stat``s the files it reads (the index, pq re-rank
vectors; coords and ids of the submaps that hold hits, before they are read) and raises
:class:`MapError` instead; a file whose modification or change time moved since the check is
checked again, and a submap whose content changed under a running process is refused from then
on (every query that needs it fails, flagged) until the map is reloaded. On a local file
system the map's folders are watched (inotify, :mod:`vlm_vpr_ros.maps.watch`): a file is
``stat``ed again only after the folder reported a change, or a second passed. The full sha256 pass
is :func:`~vlm_vpr_ros.maps.format.verify_files` (``vlm-vpr map verify``, node parameter
``verify_map``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from pathlib import Path
from typing import Any

import numpy as np

from vlm_vpr_ros import __version__
from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.files.atomic import (atomic_save_npy, atomic_save_npz, atomic_write_index,
                                      atomic_write_json)
from vlm_vpr_ros.maps import indexes
from vlm_vpr_ros.maps.format import (DOCUMENT_KEYS, MANIFEST, MAP_FORMAT, METRIC, check_content,
                                     check_ref_id, checked_file, content_error, content_matches,
                                     file_table, load_state, verify_files)
from vlm_vpr_ros.maps.mapped import IdView, load_array, prefetch_rows
from vlm_vpr_ros.maps.submap import submap_radius_km
from vlm_vpr_ros.maps.watch import FolderWatch

log = logging.getLogger(__name__)

VERSION = 2
#: the files a search of a submap of each kind reads (coords and ids: read for the hits only)
SEARCH_ROLES = {"flat": ("index",), "fp16": ("index",), "pq": ("index", "vectors")}


# -- writing ----------------------------------------------------------------------------------
def _check_ids(root: Path, rel: str, raw: np.ndarray) -> None:
    """Ids are image paths inside the images folder (issue 10's rule, as for v1 maps): a cheap
    vectorized pre-filter, then the exact check on the few suspects."""
    if raw.size == 0:
        return
    bad = (np.char.str_len(raw) == 0) | (np.char.find(raw, b"..") >= 0)
    for lead in (b"/", b"\\"):
        bad |= np.char.startswith(raw, lead)
    bad |= np.char.find(raw, b":") == 1
    for k in np.flatnonzero(bad)[:1000]:
        check_ref_id(root, rel, raw[k].decode("utf-8", "replace"))


def encode_ids(ids: list[str]) -> np.ndarray:
    """Reference ids as one fixed-width UTF-8 array (width = the longest id of the submap)."""
    raw = [str(i).encode("utf-8") for i in ids]
    if any(b"\x00" in r for r in raw):
        raise MapError("reference ids must not contain NUL characters")
    width = max([1] + [len(r) for r in raw])
    return np.array(raw, dtype=f"S{width}")


def write_submap(root: Path, sid: str, kind: str, index: Any, coords: np.ndarray,
                 ids: list[str] | np.ndarray, rerank16: np.ndarray | None) -> dict[str, str]:
    """Write one submap's files under ``root/submaps``; returns {role: relative path}."""
    rel = {"index": f"submaps/{sid}.faiss", "coords": f"submaps/{sid}.coords.npy",
           "ids": f"submaps/{sid}.ids.npy"}
    atomic_write_index(root / rel["index"], index)
    atomic_save_npy(root / rel["coords"], np.asarray(coords, dtype=np.float64).reshape(-1, 2))
    atomic_save_npy(root / rel["ids"], ids if isinstance(ids, np.ndarray) else encode_ids(ids))
    if kind == "pq":
        rel["vectors"] = f"submaps/{sid}.f16.npy"
        atomic_save_npy(root / rel["vectors"], np.asarray(rerank16, dtype=np.float16))
    return rel


def save_map(ref_map: Any, path: Path) -> dict:
    """Write an in-memory :class:`ReferenceMap` as a v2 folder; returns the manifest."""
    path.mkdir(parents=True, exist_ok=True)
    rels: list[str] = []
    if ref_map.descriptor_state:
        atomic_save_npz(path / "descriptor_state.npz", ref_map.descriptor_state)
        rels.append("descriptor_state.npz")
    subs = []
    for s in ref_map.submaps:
        files = write_submap(path, s.id, s.kind, s.index, s.coords, list(s.ids),
                             getattr(s, "rerank", None))
        rels += list(files.values())
        entry = {"id": s.id, "group": s.group or s.id, "count": s.count,
                 "centroid": [round(float(c), 7) for c in s.centroid], "kind": s.kind,
                 "radius_km": round(submap_radius_km(s), 4), "files": files}
        if getattr(s, "recall", None):
            entry["recall"] = s.recall
        subs.append(entry)
    manifest = dict(ref_map.manifest)
    manifest.pop("retired", None)  # files of the folder it was read from, not of this one
    kinds = sorted({s["kind"] for s in subs})
    manifest.update({
        "format": MAP_FORMAT, "version": VERSION, "software": f"vlm_vpr_ros {__version__}",
        "metric": METRIC, "n_references": sum(s["count"] for s in subs), "n_submaps": len(subs),
        "index": manifest.get("index", kinds[0] if len(kinds) == 1 else "auto"),
        "index_params": {"rerank_factor": int(ref_map.rerank_factor),
                         "pq": pq_name(ref_map.dim), **manifest.get("index_params", {})},
        "descriptor_state": "descriptor_state.npz" if ref_map.descriptor_state else None,
        "submaps": subs, "files": file_table(path, rels),
    })
    manifest["index_params"]["rerank_factor"] = int(ref_map.rerank_factor)
    atomic_write_json(path / MANIFEST, manifest)
    return manifest


def pq_name(dim: int) -> str:
    return indexes.pq_factory(dim)


# -- reading ----------------------------------------------------------------------------------
class LazySubmap:
    """A v2 submap: metadata from the manifest; files opened (memory-mapped) on first use."""

    def __init__(self, root: Path, entry: dict, dim: int, files_meta: dict,
                 watch: FolderWatch | None = None) -> None:
        self.root, self.dim = root, dim
        self.watch = watch  # the map's change notice (maps/watch.py); None: stat every time
        #: per ``roles`` of check_files: the watch generation in which they last passed
        self._ok_roles: dict[tuple[str, ...] | None, int] = {}
        self.id: str = entry["id"]
        self.group: str = entry.get("group") or entry["id"]
        self.count: int = int(entry["count"])
        self.centroid = tuple(float(c) for c in entry["centroid"])
        self.kind: str = entry["kind"]
        self.recall: dict | None = entry.get("recall")
        #: max distance centroid -> reference (km); None for maps written before it was stored
        self.radius_km: float | None = (float(entry["radius_km"]) if entry.get("radius_km")
                                        is not None else None)
        self.files: dict[str, str] = dict(entry["files"])
        self._sizes = {rel: int(files_meta[rel]["bytes"]) for rel in self.files.values()}
        self._meta = {rel: files_meta[rel] for rel in self.files.values()}
        #: (dev, ino, mtime_ns, ctime_ns) of each file when its content was last checked
        self._seen: dict[str, tuple[int, int, int, int]] = {}
        self._inodes: dict[str, tuple[int, int]] = {}
        self._refused = ""  # why this submap is refused (content changed under us)
        #: per ``roles`` of check_files: (rel, bytes, path) of the files it stats
        self._stat_paths: dict[tuple[str, ...] | None, list[tuple[str, int, str]]] = {}
        self._prefetch_at: dict[str, tuple[str, int, int]] | None = None  # see prefetch()
        self._lock = threading.Lock()
        self._open: tuple[Any, np.ndarray, IdView, np.ndarray | None] | None = None
        self._coords: np.ndarray | None = None  # mapped without opening the index

    # -- size guard (prevents SIGBUS on truncated mapped files) --------------------------------
    def note_checked(self) -> None:
        """Record the files' identity and times: their content was just checked."""
        for rel in self._sizes:
            with contextlib.suppress(OSError):
                st = os.stat(self.root / rel)
                self._seen[rel] = (st.st_dev, st.st_ino, st.st_mtime_ns, st.st_ctime_ns)

    def check_files(self, roles: tuple[str, ...] | None = None) -> None:
        """MapError when a file is missing, its size differs from the manifest, or it was
        modified since its content was checked and no longer matches its fingerprint (the
        submap is then refused until the map is reloaded). For an open submap, a file replaced
        by another one (new inode, e.g. an atomic map update) is not an error: the mapping keeps
        the old file alive. ``roles``: only these files (index, vectors, coords, ids: what the
        caller reads next); all by default. Files whose ``roles`` passed in the map's current
        change notice generation are not ``stat``ed again (:mod:`vlm_vpr_ros.maps.watch`)."""
        if self._refused:
            raise MapError(self._refused)
        gen = self.watch.current() if self.watch is not None else None
        if gen is not None and self._ok_roles.get(roles) == gen:
            return
        paths = self._stat_paths.get(roles)
        if paths is None:  # joined once per roles: a pathlib join per file and search cost 6x
            paths = self._stat_paths[roles] = [  # the stat itself
                (rel, self._sizes[rel], os.fspath(self.root / rel))
                for role, rel in self.files.items() if roles is None or role in roles]
        for rel, size, path in paths:
            self._check_file(rel, size, path)
        if gen is not None:
            self._ok_roles[roles] = gen

    def _check_file(self, rel: str, size: int, path: str) -> None:
        try:
            st = os.stat(path)
        except OSError as exc:
            if self._open is not None:
                return  # unlinked: the mapping keeps the data alive
            raise MapError(f"{self.root}: missing file {rel} ({exc.strerror})") from None
        if (st.st_size == size and self._seen.get(rel)
                == (st.st_dev, st.st_ino, st.st_mtime_ns, st.st_ctime_ns)):
            return  # the file whose content was checked, untouched since (most calls)
        same_file = self._inodes.get(rel) in (None, (st.st_dev, st.st_ino))
        if same_file and st.st_size != size:
            when = "after the map was opened" if self._open is not None else ""
            raise MapError(f"{self.root}: {rel} has {st.st_size} bytes, manifest says {size} "
                           f"(truncated or modified {when}); reload or rebuild the map"
                           .replace("  ", " ").replace(" )", ")"))
        now = (st.st_dev, st.st_ino, st.st_mtime_ns, st.st_ctime_ns)
        if same_file and self._seen.get(rel, now) != now:
            self._recheck(rel, now)

    def _recheck(self, rel: str, now: tuple[int, int, int, int]) -> None:
        """A file was written since its content was checked: check it again."""
        try:
            ok = content_matches(self.root / rel, self._meta[rel])
        except OSError:
            ok = False
        if ok is False:
            when = " since the map was opened" if self._open is not None else ""
            self._refused = str(content_error(self.root, rel, when)).replace(
                "the map is refused", f"submap {self.id} is refused until the map is reloaded")
            log.error("%s", self._refused)
            if self.watch is not None:
                self.watch.bump()  # memos of passed checks (ReferenceMap's) start over
            raise MapError(self._refused)
        self._seen[rel] = now  # same content (e.g. touched), or no fingerprint to compare

    def _do_open(self):
        import faiss

        self.check_files()
        root, sid = self.root, self.id
        ip = root / self.files["index"]
        flags = faiss.IO_FLAG_MMAP_IFC if self.kind in ("flat", "fp16") else 0
        try:
            index = faiss.read_index(str(ip), flags)
        except RuntimeError as exc:
            raise MapError(f"{root}: cannot read FAISS index {self.files['index']}: "
                           f"{str(exc).splitlines()[0]}") from exc
        if not isinstance(index, indexes.index_class(self.kind)):
            raise MapError(f"{root}: submap {sid} index is {type(index).__name__}, manifest "
                           f"says {self.kind!r}")
        if index.d != self.dim:
            raise MapError(f"{root}: submap {sid} index has dim {index.d}, manifest says "
                           f"{self.dim}")
        if index.ntotal != self.count:
            raise MapError(f"{root}: submap {sid} index holds {index.ntotal} vectors, manifest "
                           f"says {self.count}")
        coords = self._map_coords()
        raw = load_array(root, self.files["ids"], (self.count,), "S")
        _check_ids(root, self.files["ids"], raw)
        rerank = None
        if self.kind == "pq":
            rerank = load_array(root, self.files["vectors"], (self.count, self.dim), "f2")
        for rel in self.files.values():
            st = os.stat(root / rel)
            self._inodes[rel] = (st.st_dev, st.st_ino)
        return index, coords, IdView(raw), rerank

    def opened(self):
        if self._open is None:
            with self._lock:
                if self._open is None:
                    self._open = self._do_open()
        return self._open

    @property
    def is_open(self) -> bool:
        return self._open is not None

    @property
    def index(self) -> Any:
        return self.opened()[0]

    def _map_coords(self) -> np.ndarray:
        if self._coords is None:
            coords = load_array(self.root, self.files["coords"], (self.count, 2), "f8")
            if self.count and not np.all(np.isfinite(coords[: min(self.count, 4096)])):
                raise MapError(f"{self.root}: submap {self.id} coordinates are not finite")
            self._coords = coords
        return self._coords

    @property
    def coords(self) -> np.ndarray:
        """Reference positions, memory-mapped on their own: reading them (the posterior's
        background sample, ``map info``) does not open the index."""
        if self._open is not None:
            return self._open[1]
        self.check_files()
        return self._map_coords()

    @property
    def ids(self) -> IdView:
        return self.opened()[2]

    @property
    def rerank(self) -> np.ndarray | None:
        return self.opened()[3]

    def search(self, q: np.ndarray, k: int, factor: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-``k`` (squared L2, row). Checks the files the search reads (the index; pq: and
        the re-rank vectors); the caller checks coords and ids before reading the hits' rows
        (``ReferenceMap.search_submaps``): one stat per flat submap and query, not three."""
        return indexes.search(self._checked_index(), self.kind, self.opened()[3], q, k, factor)

    def searchable(self) -> Any:
        """The FAISS index, its files checked as :meth:`search` checks them (for
        :func:`~vlm_vpr_ros.maps.indexes.search_exact_many`)."""
        return self._checked_index()

    def _checked_index(self) -> Any:
        """The FAISS index, after a check of the files a search of this kind reads."""
        index = self.opened()[0]
        self.check_files(SEARCH_ROLES[self.kind])
        return index

    def pq_candidates(self, q: np.ndarray, kk: int) -> tuple[np.ndarray, np.ndarray]:
        """Stage 1 of a pq search; checks the index and the vectors the re-rank reads next."""
        return indexes.pq_candidates(self._checked_index(), q, kk)

    def exact_sq_l2(self, rows: np.ndarray, q: np.ndarray) -> np.ndarray:
        return indexes.exact_sq_l2(self.opened()[3], rows, q)

    def prefetch(self, rows: np.ndarray, what: tuple[str, ...] = ("vectors",)) -> None:
        """Start reading these rows of the memory-mapped files in ``what`` (roles: vectors,
        coords, ids) in the background; the next access then finds them in the page cache."""
        if self._prefetch_at is None:  # (path, row bytes, data offset) per role, once: a
            opened = self.opened()  # stat and a path join per call cost more than the advice
            arrays = {"coords": opened[1], "ids": opened[2]._raw, "vectors": opened[3]}
            self._prefetch_at = {
                role: (os.fspath(self.root / rel), arr.strides[0],
                       self._sizes[rel] - arr.nbytes)  # data to the end (npy_data_offset)
                for role, rel in self.files.items() if (arr := arrays.get(role)) is not None}
        for role in what:
            at = self._prefetch_at.get(role)
            if at is not None:
                prefetch_rows(at[0], at[1], rows, at[2])

    def vectors(self) -> np.ndarray:
        index, _, _, rerank = self.opened()
        self.check_files()
        return indexes.vectors(index, self.kind, rerank)


def validate_entries(path: Path, manifest: dict) -> None:
    """Structure of a v2 manifest and the size of every file it lists (no file is read)."""
    files = manifest["files"]
    if not isinstance(files, dict):
        raise MapError(f"{path}: manifest 'files' is not an object")
    seen = set()
    for entry in manifest["submaps"]:
        try:
            sid, kind, count, roles = entry["id"], entry["kind"], int(entry["count"]), \
                entry["files"]
            [float(c) for c in entry["centroid"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise MapError(f"{path}: malformed submap entry {str(entry)[:200]}") from exc
        if sid in seen:
            raise MapError(f"{path}: duplicate submap id {sid!r}")
        seen.add(sid)
        if kind not in indexes.SUBMAP_KINDS or count < 0:
            raise MapError(f"{path}: submap {sid}: kind {kind!r} / count {count} invalid")
        need = {"index", "coords", "ids"} | ({"vectors"} if kind == "pq" else set())
        if not isinstance(roles, dict) or not need <= set(roles):
            raise MapError(f"{path}: submap {sid} lacks files {sorted(need - set(roles or {}))}")
        for rel in roles.values():
            checked_file(path, manifest, rel, False)
    if manifest.get("descriptor_state"):
        checked_file(path, manifest, manifest["descriptor_state"], False)


def open_submaps(path: Path, manifest: dict, verify: bool
                 ) -> tuple[list["LazySubmap"], dict[str, np.ndarray]]:
    """The lazy submaps and the descriptor state of a v2 folder (for ``ReferenceMap.load``):
    the manifest's structure, every file's size and its content fingerprint are checked;
    ``verify`` checks the sha256 of every byte instead."""
    validate_entries(path, manifest)
    dim = int(manifest["descriptor"]["dim"])
    # watched before the check: a change made during it is seen at the first search
    watch = FolderWatch(sorted({(path / r).parent for e in manifest["submaps"]
                                for r in e["files"].values()}))
    subs = [LazySubmap(path, e, dim, manifest["files"], watch) for e in manifest["submaps"]]
    for s in subs:  # before the check: a change made during it is seen at the first search
        s.note_checked()
    rels = [r for e in manifest["submaps"] for r in e["files"].values()]
    rels += [r for r in (manifest.get(k) for k in ("descriptor_state",) + DOCUMENT_KEYS)
             if isinstance(r, str) and r in manifest["files"]]
    if verify:
        verify_files(path, manifest)
    else:
        unchecked = check_content(path, manifest, rels)
        if unchecked:
            log.info("%s: %d of %d files were written before content fingerprints and are "
                     "checked by size only ('vlm-vpr map verify' checks them whole)", path,
                     unchecked, len(rels))
    state = load_state(path, manifest, False)
    total = sum(s.count for s in subs)
    if total != manifest["n_references"]:
        raise MapError(f"{path}: submaps hold {total} references, manifest says "
                       f"{manifest['n_references']}")
    return subs, state
