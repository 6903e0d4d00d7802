"""Validation when loading a map folder: every mismatch is a MapError with a clear message."""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from vlm_vpr_ros.errors import MapError

REQUIRED_KEYS = ("format", "version", "descriptor", "metric", "partition", "n_references",
                 "submaps", "files")


def read_manifest(path: Path) -> dict:
    from vlm_vpr_ros.map_io import MANIFEST, MAP_FORMAT, METRIC, SUPPORTED_VERSIONS

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
    part = need(manifest["partition"], "partition", dict, "an object {method, params}")
    need(part.get("method"), "partition.method", str, "a string")
    need(manifest["n_references"], "n_references", int, "an integer")
    state = manifest.get("descriptor_state")
    if state is not None:
        check_map_relpath(mpath, "descriptor_state", state)
    if "index" in manifest:
        need(manifest["index"], "index", str, "a string")
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
        sfiles = need(entry.get("files"), f"{where}.files", dict,
                      "an object {index, coords, ids}")
        for key in ("index", "coords", "ids"):
            if key not in sfiles:
                raise MapError(f"{mpath}: manifest field '{where}.files' lacks {key!r}")
            check_map_relpath(mpath, f"{where}.files.{key}", sfiles[key])


def _file(path: Path, manifest: dict, rel: str, verify: bool) -> Path:
    from vlm_vpr_ros.map_io import sha256_file

    p = path / rel
    meta = manifest["files"].get(rel)
    if meta is None:
        raise MapError(f"{path}: {rel} is not listed in the manifest")
    if not p.is_file():
        raise MapError(f"{path}: missing file {rel}")
    size = p.stat().st_size
    if size != meta.get("bytes"):
        raise MapError(f"{path}: {rel} has {size} bytes, manifest says {meta.get('bytes')} "
                       "(truncated or modified)")
    if verify and sha256_file(p) != meta.get("sha256"):
        raise MapError(f"{path}: {rel} checksum mismatch (corrupt or modified)")
    return p


def _check_ref_id(path: Path, rel: str, ref_id: Any) -> None:
    """Reference ids are image paths relative to the images folder: never absolute, no '..'."""
    if not isinstance(ref_id, str) or not ref_id:
        raise MapError(f"{path}: {rel}: reference id {ref_id!r} is not a file name")
    parts = ref_id.replace("\\", "/").split("/")
    if ref_id.startswith(("/", "\\")) or ".." in parts or re.match(r"^[A-Za-z]:", ref_id):
        raise MapError(f"{path}: {rel}: reference id {ref_id!r} points outside the images "
                       "folder")


def load_state(path: Path, manifest: dict, verify: bool) -> dict[str, np.ndarray]:
    rel = manifest.get("descriptor_state")
    if not rel:
        return {}
    p = _file(path, manifest, rel, verify)
    try:
        with np.load(p, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise MapError(f"{path}: cannot read {rel}: {exc}") from exc


def load_submap(path: Path, manifest: dict, entry: Any, verify: bool):
    import faiss

    from vlm_vpr_ros.map_io import Submap

    try:
        sid, count, centroid, files = (entry["id"], int(entry["count"]),
                                       tuple(float(c) for c in entry["centroid"]), entry["files"])
    except (KeyError, TypeError, ValueError) as exc:
        raise MapError(f"{path}: malformed submap entry {entry!r}") from exc
    dim = manifest["descriptor"]["dim"]
    ip = _file(path, manifest, files["index"], verify)
    try:
        index = faiss.deserialize_index(np.fromfile(ip, dtype=np.uint8))
    except RuntimeError as exc:
        raise MapError(f"{path}: cannot read FAISS index {files['index']}: "
                       f"{str(exc).splitlines()[0]}") from exc
    kind = manifest.get("index", "flat")
    expected = {"flat": faiss.IndexFlatL2, "fp16": faiss.IndexScalarQuantizer}.get(kind)
    if expected is None or not isinstance(index, expected):
        raise MapError(f"{path}: submap {sid} index is {type(index).__name__}, manifest says "
                       f"{kind!r}")
    if index.d != dim:
        raise MapError(f"{path}: submap {sid} index has dim {index.d}, manifest says {dim}")
    if index.ntotal != count:
        raise MapError(f"{path}: submap {sid} index holds {index.ntotal} vectors, manifest "
                       f"says {count}")
    cp = _file(path, manifest, files["coords"], verify)
    try:
        coords = np.load(cp, allow_pickle=False)
        if not isinstance(coords, np.ndarray):  # an .npz under a .npy name
            raise ValueError("not a .npy array")
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise MapError(f"{path}: cannot read {files['coords']}: {exc}") from exc
    if coords.shape != (count, 2) or not np.all(np.isfinite(coords)):
        raise MapError(f"{path}: submap {sid} coordinates have shape {coords.shape}, "
                       f"expected ({count}, 2) finite values")
    idp = _file(path, manifest, files["ids"], verify)
    try:
        ids = json.loads(idp.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapError(f"{path}: corrupt {files['ids']}: {exc}") from exc
    if not isinstance(ids, list) or len(ids) != count:
        raise MapError(f"{path}: submap {sid} has {len(ids) if isinstance(ids, list) else '?'} "
                       f"ids, expected {count}")
    suspects = [i for i in ids if not isinstance(i, str) or not i or i[0] in "/\\"
                or ".." in i or i[1:2] == ":"]  # cheap pre-filter (millions of ids)
    for ref_id in suspects:
        _check_ref_id(path, files["ids"], ref_id)
    return Submap(sid, centroid, coords.astype(np.float64), [str(i) for i in ids], index,
                  kind=kind)
