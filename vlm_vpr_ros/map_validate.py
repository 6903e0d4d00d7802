"""Validation when loading a map folder: every mismatch is a MapError with a clear message."""

from __future__ import annotations

import json
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
    return manifest


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


def load_state(path: Path, manifest: dict, verify: bool) -> dict[str, np.ndarray]:
    rel = manifest.get("descriptor_state")
    if not rel:
        return {}
    p = _file(path, manifest, rel, verify)
    try:
        with np.load(p, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (OSError, ValueError) as exc:
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
    except (OSError, ValueError) as exc:
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
    return Submap(sid, centroid, coords.astype(np.float64), [str(i) for i in ids], index,
                  kind=kind)
