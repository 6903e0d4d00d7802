"""JSON documents a map carries beside its index (the fusion's ``calibration.json``, the
verification's ``verification.json``): listed in the manifest's ``files`` and named by a
manifest key, read with the size/sha256 check of every map file, written atomically with the
manifest last."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Mapping

from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.files.atomic import atomic_write_json
from vlm_vpr_ros.maps.format import MANIFEST, checked_file, file_table

log = logging.getLogger(__name__)


def load_document(ref_map: Any, key: str, what: str) -> Any | None:
    """The parsed document the manifest names under ``key`` (checksum-checked), or None when
    the map has none (or a later rewrite of the map no longer lists it: logged)."""
    rel = ref_map.manifest.get(key)
    if not rel or ref_map.path is None:
        return None
    if rel not in ref_map.manifest.get("files", {}):
        log.warning("%s: %s is no longer listed in the manifest; %s is not used", ref_map.path,
                    rel, what)
        return None
    p = checked_file(Path(ref_map.path), ref_map.manifest, rel, True)
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapError(f"{p}: corrupt {what} ({exc})") from None


def save_document(ref_map: Any, key: str, name: str, doc: Mapping[str, Any], what: str) -> Path:
    """Write ``name`` into the saved map, list it in ``files`` and under ``key`` (manifest
    last); ``ref_map.manifest`` follows."""
    if ref_map.path is None:
        raise MapError(f"save the map before writing its {what}")
    path = Path(ref_map.path)
    atomic_write_json(path / name, dict(doc))
    manifest = dict(ref_map.manifest)
    files = dict(manifest.get("files", {}))
    files.update(file_table(path, [name]))
    manifest["files"], manifest[key] = files, name
    atomic_write_json(path / MANIFEST, manifest)
    ref_map.manifest = manifest
    return path / name
