"""Map format version 1: read (fully into memory) and written for compatibility tests.

New maps are written in version 2 (:mod:`vlm_vpr_ros.maps.store`); ``vlm-vpr map upgrade``
converts a v1 map. Version 1 layout::

    MAP/manifest.json              format, version, descriptor identity, metric, partition, counts,
                                   submap centroids, size + sha256 of every file
    MAP/descriptor_state.npz       fitted descriptor state (codebook, PCA), if any (no pickle)
    MAP/submaps/<id>.faiss         exact L2 FAISS index of the submap's descriptors (IndexFlatL2,
                                   or fp16 IndexScalarQuantizer with ``--index fp16``)
    MAP/submaps/<id>.coords.npy    (n, 2) float64 lat/lon
    MAP/submaps/<id>.ids.json      reference ids (image paths relative to the images folder)
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from vlm_vpr_ros import __version__
from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.files.atomic import (atomic_save_npy, atomic_save_npz, atomic_write_index,
                                      atomic_write_json)
from vlm_vpr_ros.maps.format import (MANIFEST, MAP_FORMAT, METRIC, check_ref_id, checked_file,
                                     file_table)
from vlm_vpr_ros.maps.submap import Submap


def load_submap(path: Path, manifest: dict, entry: Any, verify: bool):
    import faiss

    try:
        sid, count, centroid, files = (entry["id"], int(entry["count"]),
                                       tuple(float(c) for c in entry["centroid"]), entry["files"])
    except (KeyError, TypeError, ValueError) as exc:
        raise MapError(f"{path}: malformed submap entry {entry!r}") from exc
    dim = manifest["descriptor"]["dim"]
    ip = checked_file(path, manifest, files["index"], verify)
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
    cp = checked_file(path, manifest, files["coords"], verify)
    try:
        coords = np.load(cp, allow_pickle=False)
        if not isinstance(coords, np.ndarray):  # an .npz under a .npy name
            raise ValueError("not a .npy array")
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise MapError(f"{path}: cannot read {files['coords']}: {exc}") from exc
    if coords.shape != (count, 2) or not np.all(np.isfinite(coords)):
        raise MapError(f"{path}: submap {sid} coordinates have shape {coords.shape}, "
                       f"expected ({count}, 2) finite values")
    idp = checked_file(path, manifest, files["ids"], verify)
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
        check_ref_id(path, files["ids"], ref_id)
    return Submap(sid, centroid, coords.astype(np.float64), [str(i) for i in ids], index,
                  kind=kind)


def save_v1(ref_map: Any, path: str | os.PathLike[str]) -> None:
    """Write format version 1 (flat/fp16 only): kept for compatibility tests and tools."""
    path = Path(path)
    (path / "submaps").mkdir(parents=True, exist_ok=True)
    files: dict[str, dict] = {}
    if ref_map.descriptor_state:
        atomic_save_npz(path / "descriptor_state.npz", ref_map.descriptor_state)
        files["descriptor_state.npz"] = {}
    subs = []
    for s in ref_map.submaps:
        rel = {"index": f"submaps/{s.id}.faiss", "coords": f"submaps/{s.id}.coords.npy",
               "ids": f"submaps/{s.id}.ids.json"}
        atomic_write_index(path / rel["index"], s.index)
        atomic_save_npy(path / rel["coords"], np.asarray(s.coords, dtype=np.float64))
        atomic_write_json(path / rel["ids"], list(s.ids))
        files.update({v: {} for v in rel.values()})
        subs.append({"id": s.id, "count": s.count,
                     "centroid": [round(float(c), 7) for c in s.centroid], "files": rel})
    files = file_table(path, list(files))
    manifest = dict(ref_map.manifest)
    manifest.update({
        "format": MAP_FORMAT, "version": 1, "software": f"vlm_vpr_ros {__version__}",
        "metric": METRIC, "n_references": ref_map.n_references, "n_submaps": len(subs),
        "descriptor_state": "descriptor_state.npz" if ref_map.descriptor_state else None,
        "submaps": subs, "files": files,
    })
    atomic_write_json(path / MANIFEST, manifest)
