"""The map folder's contract: format constants, the manifest, and the checks made at load.

Every mismatch is a :class:`~vlm_vpr_ros.errors.MapError` with a message naming the file or
manifest field.

Content checks (on by default, :func:`check_content`): sizes alone miss files swapped between
submaps or rewritten in place with the same size, and the full sha256 pass (``map verify``) reads
every byte. So every file's manifest entry also carries a fingerprint that is cheap to check:
files up to :data:`SMALL_FILE_BYTES` are checked whole against their sha256; larger ones against
``sample``, the sha256 of their size and :data:`SAMPLE_PAGES` pages (first, last and evenly
spaced between; the first page of a ``.npy``/FAISS file holds its header and first rows). A file
that differs anywhere in a sampled page, or whose first rows differ (any swap), is caught; a
change confined to unsampled pages is left to ``map verify``. Maps written before fingerprints
existed have no ``sample``: their small files are still checked by sha256, the others by size.
The layouts of the two format versions are described in :mod:`vlm_vpr_ros.maps.store`
(version 2, written today) and :mod:`vlm_vpr_ros.maps.v1`.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import zipfile
from pathlib import Path
from typing import Any, Callable, Mapping

try:
    import resource
except ImportError:  # pragma: no cover - not POSIX: no descriptor limit to ask
    resource = None

import numpy as np

from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.files.atomic import file_sha256

MAP_FORMAT = "vlm_vpr_ros.map"
MAP_VERSION = 2  # written; see maps/store.py
SUPPORTED_VERSIONS = (1, 2)
METRIC = "squared_l2"
MANIFEST = "manifest.json"
#: identity keys that must agree between a map and the query-time descriptor
IDENTITY_KEYS = ("name", "dim", "release", "preprocessing")
REQUIRED_KEYS = ("format", "version", "descriptor", "metric", "partition", "n_references",
                 "submaps", "files")
#: manifest keys naming a JSON document of the map (:mod:`vlm_vpr_ros.maps.documents`)
DOCUMENT_KEYS = ("calibration", "verification_calibration")
#: files up to this size are checked whole (sha256) when a map is opened
SMALL_FILE_BYTES = 256 * 1024
#: larger files: the sha256 of this many 4 KiB pages (and the size) is their fingerprint
SAMPLE_PAGES = 4
PAGE_BYTES = 4096
#: at most this many files open at once in a content check (fewer under a low descriptor limit)
CHECK_BATCH_FILES = 256
_SAMPLE_TAG = b"vlm_vpr_ros.sample.v1"


def read_manifest(path: Path) -> dict:
    if not path.is_dir():
        raise MapError(f"map folder not found: {path}")
    mpath = path / MANIFEST
    if not mpath.is_file():
        raise MapError(f"{path} is not a map (no {MANIFEST}); build one with 'vlm-vpr build-map'")
    try:
        manifest = json.loads(mpath.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapError(f"{mpath}: corrupt manifest ({exc})") from exc
    if not isinstance(manifest, dict):
        raise MapError(f"{mpath}: manifest is not a JSON object")
    missing = [k for k in REQUIRED_KEYS if k not in manifest]
    if missing:
        raise MapError(f"{mpath}: manifest lacks {missing}")
    if manifest["format"] != MAP_FORMAT:
        raise MapError(f"{mpath}: format {manifest['format']!r}, expected {MAP_FORMAT!r}")
    if manifest["version"] not in SUPPORTED_VERSIONS:
        raise MapError(f"{mpath}: map format version {manifest['version']} is not supported "
                       f"(this software reads versions {SUPPORTED_VERSIONS}); rebuild the map")
    if manifest["metric"] != METRIC:
        raise MapError(f"{mpath}: metric {manifest['metric']!r} unsupported")
    desc = manifest["descriptor"]
    if not isinstance(desc, dict) or not isinstance(desc.get("dim"), int) or desc["dim"] <= 0:
        raise MapError(f"{mpath}: descriptor entry lacks a positive integer 'dim'")
    check_structure(manifest, mpath)
    return manifest


def _type_error(mpath: Path, field: str, expected: str, value: Any) -> MapError:
    return MapError(f"{mpath}: manifest field {field!r} must be {expected}, got "
                    f"{type(value).__name__} {str(value)[:60]!r}")


def check_map_relpath(mpath: Path, field: str, rel: Any) -> str:
    """A file named by the manifest: a relative path inside the map folder."""
    if not isinstance(rel, str) or not rel:
        raise _type_error(mpath, field, "a relative file path", rel)
    parts = rel.replace("\\", "/").split("/")
    if rel.startswith(("/", "\\")) or ".." in parts or re.match(r"^[A-Za-z]:", rel) or "\0" in rel:
        raise MapError(f"{mpath}: manifest field {field!r} = {rel!r} points outside the map "
                       "folder")
    return rel


def check_structure(manifest: dict, mpath: Path) -> None:
    """Types of every field the loader reads (not just their values): a hand-edited manifest
    gives a MapError naming the field, never a TypeError deep in the loader."""
    def need(value: Any, field: str, types: type | tuple, expected: str) -> Any:
        if not isinstance(value, types) or isinstance(value, bool) and bool not in (
                types if isinstance(types, tuple) else (types,)):
            raise _type_error(mpath, field, expected, value)
        return value

    files = need(manifest["files"], "files", dict, "an object {path: {bytes, sha256}}")
    for rel, meta in files.items():
        check_map_relpath(mpath, f"files[{rel!r}]", rel)
        need(meta, f"files[{rel!r}]", dict, "an object {bytes, sha256}")
        need(meta.get("bytes"), f"files[{rel!r}].bytes", int, "an integer")
        need(meta.get("sha256"), f"files[{rel!r}].sha256", str, "a string")
        if "sample" in meta:
            need(meta["sample"], f"files[{rel!r}].sample", str, "a string")
    part = need(manifest["partition"], "partition", dict, "an object {method, params}")
    need(part.get("method"), "partition.method", str, "a string")
    need(manifest["n_references"], "n_references", int, "an integer")
    need(manifest["descriptor"].get("name"), "descriptor.name", str, "a string")
    state = manifest.get("descriptor_state")
    if state is not None:
        check_map_relpath(mpath, "descriptor_state", state)
    for key in DOCUMENT_KEYS:
        if manifest.get(key) is not None:
            check_map_relpath(mpath, key, manifest[key])
    for k, rel in enumerate(need(manifest.get("retired", []), "retired", list,
                                 "a list of file paths")):
        check_map_relpath(mpath, f"retired[{k}]", rel)  # an edit deletes them
    if "index" in manifest:
        need(manifest["index"], "index", str, "a string")
    if "index_params" in manifest:
        params = need(manifest["index_params"], "index_params", dict,
                      "an object {rerank_factor, ...}")
        if "rerank_factor" in params and (need(params["rerank_factor"],
                                               "index_params.rerank_factor", int,
                                               "an integer") < 1):
            raise _type_error(mpath, "index_params.rerank_factor", "an integer >= 1",
                              params["rerank_factor"])
    if "generation" in manifest and need(manifest["generation"], "generation", int,
                                         "an integer") < 0:
        raise _type_error(mpath, "generation", "an integer >= 0", manifest["generation"])
    if manifest.get("source") is not None:
        src = need(manifest["source"], "source", dict, "an object")
        if "skipped" in src:
            need(src["skipped"], "source.skipped", list, "a list")
    subs = need(manifest["submaps"], "submaps", list, "a list of submap entries")
    seen: set[str] = set()
    for k, entry in enumerate(subs):
        where = f"submaps[{k}]"
        need(entry, where, dict, "an object {id, count, centroid, files}")
        sid = need(entry.get("id"), f"{where}.id", str, "a string")
        if sid in seen:
            raise MapError(f"{mpath}: manifest field '{where}.id' repeats submap {sid!r}")
        seen.add(sid)
        count = need(entry.get("count"), f"{where}.count", int, "an integer")
        if count < 0:
            raise _type_error(mpath, f"{where}.count", "a count >= 0", count)
        cen = need(entry.get("centroid"), f"{where}.centroid", list, "[lat, lon]")
        if len(cen) != 2 or not all(isinstance(c, (int, float)) and not isinstance(c, bool)
                                    for c in cen):
            raise _type_error(mpath, f"{where}.centroid", "[lat, lon] numbers", cen)
        for key in ("group", "kind"):
            if key in entry:
                need(entry[key], f"{where}.{key}", str, "a string")
        if entry.get("recall") is not None:
            rec = need(entry["recall"], f"{where}.recall", dict,
                       "an object {recall_at_1, recall_at_50}")
            for key in ("recall_at_1", "recall_at_50"):
                need(rec.get(key), f"{where}.recall.{key}", (int, float), "a number")
        sfiles = need(entry.get("files"), f"{where}.files", dict,
                      "an object {index, coords, ids}")
        for key in ("index", "coords", "ids"):
            if key not in sfiles:
                raise MapError(f"{mpath}: manifest field '{where}.files' lacks {key!r}")
            check_map_relpath(mpath, f"{where}.files.{key}", sfiles[key])


def checked_file(path: Path, manifest: Mapping[str, Any], rel: str, verify: bool) -> Path:
    """The path of a file the manifest lists, after checking that it exists with the listed
    size (and, with ``verify``, the listed sha256)."""
    p = path / rel
    meta = manifest["files"].get(rel)
    if not isinstance(meta, dict) or not isinstance(meta.get("bytes"), int):
        raise MapError(f"{path}: {rel} is not listed in the manifest")
    if ".." in Path(rel).parts or Path(rel).is_absolute():
        raise MapError(f"{path}: file {rel!r} is outside the map folder")
    try:
        size = p.stat().st_size
    except OSError:
        raise MapError(f"{path}: missing file {rel}") from None
    if size != meta["bytes"]:
        raise MapError(f"{path}: {rel} has {size} bytes, manifest says {meta['bytes']} "
                       "(truncated or modified)")
    if verify and file_sha256(p) != meta.get("sha256"):
        raise MapError(f"{path}: {rel} checksum mismatch (corrupt or modified)")
    return p


def sample_offsets(size: int) -> list[int]:
    """Start of each sampled page of a file of ``size`` bytes (page-aligned, first and last
    included)."""
    last = max(0, (size - 1) // PAGE_BYTES)
    n = min(SAMPLE_PAGES, last + 1)
    pages = sorted({round(i * last / max(1, n - 1)) for i in range(n)})
    return [p * PAGE_BYTES for p in pages]


def _digest_fd(fd: int, size: int) -> str:
    h = hashlib.sha256(_SAMPLE_TAG)
    h.update(str(size).encode())
    for off in sample_offsets(size):
        h.update(os.pread(fd, PAGE_BYTES, off))
    return h.hexdigest()


def sample_digest(path: str | os.PathLike[str], size: int | None = None) -> str:
    """Fingerprint of a large file: sha256 of its size and its sampled pages."""
    fd = os.open(path, os.O_RDONLY)
    try:
        return _digest_fd(fd, os.fstat(fd).st_size if size is None else size)
    finally:
        os.close(fd)


def file_entry(root: Path, rel: str) -> dict:
    """The manifest's ``files`` entry of ``root/rel``: bytes, sha256 and (large files) the
    sampled-page fingerprint checked at every open."""
    p = root / rel
    size = p.stat().st_size
    entry: dict[str, Any] = {"bytes": size, "sha256": file_sha256(p)}
    if size > SMALL_FILE_BYTES:
        entry["sample"] = sample_digest(p, size)
    return entry


def file_table(root: Path, rels: list[str]) -> dict[str, dict]:
    """The manifest's ``files`` entries (size, sha256, fingerprint) of files under ``root``."""
    return {r: file_entry(root, r) for r in rels}


def content_matches(path: str | os.PathLike[str], meta: Mapping[str, Any]) -> bool | None:
    """Whether a file still matches its manifest entry by the cheap check (small: sha256;
    large: sampled pages); None when the entry has no fingerprint (an older map)."""
    size = int(meta["bytes"])
    if size <= SMALL_FILE_BYTES:
        return file_sha256(path) == meta.get("sha256")
    if not isinstance(meta.get("sample"), str):
        return None
    return sample_digest(path, size) == meta["sample"]


def check_content(path: Path, manifest: Mapping[str, Any], rels: list[str]) -> int:
    """The cheap content check of ``rels`` (module docstring); MapError naming the first file
    that differs. Returns how many files had no fingerprint (maps written before them).

    Files are handled in batches: open, queue the reads of the sampled pages
    (``posix_fadvise(WILLNEED)``: a cold disk serves them in parallel), then hash."""
    files, root = manifest["files"], os.fspath(path)
    todo = [r for r in rels if isinstance(files[r].get("sample"), str)
            or int(files[r]["bytes"]) <= SMALL_FILE_BYTES]
    unchecked = len(rels) - len(todo)
    step = _batch_files()
    for start in range(0, len(todo), step):
        batch, fds = todo[start:start + step], []
        try:
            for rel in batch:
                try:
                    fds.append(os.open(os.path.join(root, rel), os.O_RDONLY))
                except OSError as exc:
                    raise MapError(f"{path}: cannot read {rel} ({exc.strerror})") from None
                size = int(files[rel]["bytes"])
                _advise(fds[-1], [0] if size <= SMALL_FILE_BYTES else sample_offsets(size),
                        min(size, SMALL_FILE_BYTES) if size <= SMALL_FILE_BYTES else PAGE_BYTES)
            for rel, fd in zip(batch, fds):
                meta, size = files[rel], int(files[rel]["bytes"])
                try:
                    if size <= SMALL_FILE_BYTES:
                        with os.fdopen(os.dup(fd), "rb") as fh:
                            ok = hashlib.file_digest(fh, "sha256").hexdigest() == meta["sha256"]
                    else:
                        ok = _digest_fd(fd, size) == meta["sample"]
                except OSError as exc:
                    raise MapError(f"{path}: cannot read {rel} ({exc.strerror})") from None
                if not ok:
                    raise content_error(path, rel)
        finally:
            for fd in fds:
                os.close(fd)
    return unchecked


def _batch_files() -> int:
    """How many files :func:`check_content` opens at once: :data:`CHECK_BATCH_FILES`, or an
    eighth of the process's soft descriptor limit when that is fewer (a map is opened beside
    cameras, sockets and another map's files)."""
    if resource is None:
        return CHECK_BATCH_FILES
    soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    return CHECK_BATCH_FILES if soft == resource.RLIM_INFINITY else max(
        1, min(CHECK_BATCH_FILES, soft // 8))


def _advise(fd: int, offsets: list[int], length: int) -> None:
    if hasattr(os, "posix_fadvise"):
        for off in offsets:
            try:
                os.posix_fadvise(fd, off, length, os.POSIX_FADV_WILLNEED)
            except OSError:
                return


def content_error(path: Path, rel: str, when: str = "") -> MapError:
    return MapError(f"{path}: {rel} does not match the manifest{when} (swapped with another "
                    "file or rewritten in place); the map is refused: rebuild it or run "
                    "'vlm-vpr map verify'")


def verify_files(path: Path, manifest: Mapping[str, Any],
                 progress: Callable[[str], Any] | None = None) -> list[str]:
    """sha256 of every listed file against the manifest (``vlm-vpr map verify``); raises
    MapError naming the first bad one. Returns the files checked."""
    checked = []
    for rel in manifest["files"]:
        checked_file(path, manifest, rel, True)
        checked.append(rel)
        if progress is not None:
            progress(rel)
    return checked


def bad_ref_id(ref_id: Any) -> bool:
    """Reference ids are image paths relative to the images folder: never empty or absolute,
    no ``..``, no drive letter, no NUL."""
    if not isinstance(ref_id, str) or not ref_id.strip():
        return True
    parts = re.split(r"[/\\]", ref_id)
    return (ref_id.startswith(("/", "\\")) or ".." in parts
            or re.match(r"^[A-Za-z]:", ref_id) is not None or "\0" in ref_id)


def check_ref_id(path: Path, rel: str, ref_id: Any) -> None:
    """MapError when a stored reference id points outside the images folder."""
    if not isinstance(ref_id, str) or not ref_id:
        raise MapError(f"{path}: {rel}: reference id {ref_id!r} is not a file name")
    if bad_ref_id(ref_id):
        raise MapError(f"{path}: {rel}: reference id {ref_id!r} points outside the images "
                       "folder")


def load_state(path: Path, manifest: dict, verify: bool) -> dict[str, np.ndarray]:
    rel = manifest.get("descriptor_state")
    if not rel:
        return {}
    p = checked_file(path, manifest, rel, False)
    try:
        data = p.read_bytes()  # read whole anyway: its sha256 is checked at every open
    except OSError as exc:
        raise MapError(f"{path}: cannot read {rel}: {exc.strerror}") from None
    if hashlib.sha256(data).hexdigest() != manifest["files"][rel].get("sha256"):
        raise content_error(path, rel)
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise MapError(f"{path}: cannot read {rel}: {exc}") from exc


def check_descriptor_identity(map_identity: Mapping[str, Any],
                              query_identity: Mapping[str, Any]) -> None:
    """Raise MapError when a query-time descriptor would not be comparable with the map's."""
    diffs = [k for k in IDENTITY_KEYS
             if map_identity.get(k) != query_identity.get(k)]
    if diffs:
        detail = "; ".join(f"{k}: map={map_identity.get(k)!r} query={query_identity.get(k)!r}"
                           for k in diffs)
        raise MapError(f"descriptor mismatch between map and query ({detail})")
