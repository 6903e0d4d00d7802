"""JSON documents a map carries beside its index (the fusion's ``calibration.json``, the
verification's ``verification.json``): listed in the manifest's ``files`` and named by a
manifest key, read with the size/sha256 check of every map file, written atomically with the
manifest last."""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import re
import shutil
from pathlib import Path
from typing import Any, Mapping

from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.files.atomic import atomic_write_bytes, atomic_write_json
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
    """Write ``doc`` into the saved map, list it in ``files`` and under ``key``; the manifest
    is replaced last (the commit point). ``ref_map.manifest`` follows.

    A file the manifest lists is never rewritten in place (a kill between the two writes would
    leave a map whose content check refuses it): a rewrite goes to a new, content-named file
    (``calibration.<sha256[:12]>.json``), the one it replaces is listed in ``retired`` and kept
    one more generation for readers of the previous manifest, like the files of a map edit
    (:mod:`vlm_vpr_ros.maps.transaction`). The first write of a fresh map uses ``name``."""
    if ref_map.path is None:
        raise MapError(f"save the map before writing its {what}")
    path = Path(ref_map.path)
    manifest = dict(ref_map.manifest)
    files = dict(manifest.get("files", {}))
    data = (json.dumps(dict(doc), indent=2) + "\n").encode("utf-8")
    rel = name
    if name in files or name in manifest.get("retired", []):
        stem, dot, ext = name.rpartition(".")
        rel = f"{stem}.{hashlib.sha256(data).hexdigest()[:12]}{dot}{ext}"
    atomic_write_bytes(path / rel, data)
    old = manifest.get(key)
    files.update(file_table(path, [rel]))
    retired = [r for r in manifest.get("retired", []) if r != rel]
    stale: list[str] = []
    if isinstance(old, str) and old != rel and old in files:
        del files[old]
        stale = [r for r in retired if _same_document(r, name) and r not in files]
        retired = [r for r in retired if r not in stale] + [old]
    manifest["files"], manifest[key] = files, rel
    if retired or "retired" in manifest:
        manifest["retired"] = retired
    atomic_write_json(path / MANIFEST, manifest)
    ref_map.manifest = manifest
    for r in stale:  # retired by the save before: two generations old now
        with contextlib.suppress(FileNotFoundError):
            (path / r).unlink()
    return path / rel


def _same_document(rel: str, name: str) -> bool:
    """Whether ``rel`` is ``name`` or one of its content-named rewrites."""
    stem, _, ext = name.rpartition(".")
    return rel == name or re.fullmatch(re.escape(stem) + r"\.[0-9a-f]{12}\." + re.escape(ext),
                                       rel) is not None


def carry_companions(src: Path, src_manifest: Mapping[str, Any], dst: Path) -> list[str]:
    """Copy into the saved map ``dst`` the files of the map ``src`` that are not its submaps'
    indexes (the calibration documents, the local-feature store, the image index and the
    images), and list them in ``dst``'s manifest: ``map upgrade`` writes new indexes for the
    same submaps (same ids, same rows), so these stay valid. Returns the files carried."""
    man = json.loads((dst / MANIFEST).read_text(encoding="utf-8"))
    files = src_manifest.get("files")
    listed = list(files) if isinstance(files, dict) else []  # v1 manifests list per submap
    listed += [src_manifest[k] for k in ("calibration", "verification_calibration")
               if isinstance(src_manifest.get(k), str) and src_manifest[k] not in listed]
    indexes = {rel for s in src_manifest.get("submaps", [])
               for rel in ((s.get("files") or {}).values() if isinstance(s, dict) else ())}
    carried = [rel for rel in listed if rel not in indexes and rel not in man["files"]
               and (src / rel).is_file()]
    images = (src_manifest.get("images") or {}).get("folder")
    if images and (src / images).is_dir():  # the images, listed in their own index (carried)
        shutil.copytree(src / images, dst / images, dirs_exist_ok=True)
    for rel in carried:
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src / rel, dst / rel)
    man["files"].update(file_table(dst, carried))
    atomic_write_json(dst / MANIFEST, man)
    return carried
