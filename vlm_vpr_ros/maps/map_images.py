"""Reference images kept inside a map (teach maps built from a bag): ``MAP/images/<id>``,
listed with size and sha256 in ``MAP/images/index.g<generation>.json`` (itself in the
manifest's ``files``). Adding to such a map copies the new images in; removing deletes them."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any, Mapping, Sequence

from vlm_vpr_ros.errors import DataError, MapError
from vlm_vpr_ros.files.atomic import atomic_path, atomic_write_json, file_sha256
from vlm_vpr_ros.maps.format import MANIFEST, bad_ref_id, checked_file
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.maps.transaction import Transaction, edit_lock

IMAGES_DIR = "images"


def images_folder(map_dir: str | os.PathLike[str] | None, manifest: Mapping[str, Any],
                  override: str | os.PathLike[str] = "") -> Path | None:
    """Where a map's reference images are: ``override`` when given (the node's
    ``reference_images_dir``, ``--reference-images``: the folder the map was built from), else
    the map's own images folder (teach maps keep their pictures), else None. Verification of
    maps without stored features, ``--save-matches`` and the node's debug view all look here."""
    if override:
        return Path(override).expanduser()
    entry = manifest.get("images") or {}
    if map_dir is not None and entry:
        return Path(map_dir) / entry.get("folder", IMAGES_DIR)
    return None


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
