"""Growing and shrinking a map in place: ``vlm-vpr map add`` / ``map remove``.

An edit keeps the map's descriptor state (codebook, PCA): new references are described exactly
as the map's own were, so a map can grow drive by drive without being rebuilt. New references
join the submap their position belongs to (same country; nearest K-means centroid when within
``FIT_SLACK`` times that submap's radius, at least ``FIT_FLOOR_M``); those that fit none form new
submaps. Only the affected submaps are rewritten.

Atomicity: every file an edit writes has a new name (``submaps/<id>.g<generation>.*``), the
manifest is replaced last with ``os.replace`` (the commit point). The files it no longer lists
stay one more generation (manifest ``retired``) so that a reader of the previous manifest —
a node that opened submaps lazily — keeps a complete map until it reloads; the next edit
deletes them. An edit that fails before the commit deletes what it wrote and leaves the old
map as it was. One writer at a time: the map's writer lock (``PARENT/.MAP.lock``,
:mod:`vlm_vpr_ros.files.lock`), shared with ``build-map``.

Maps may hold their reference images (teach maps built from a bag,
:mod:`vlm_vpr_ros.maps.map_images`): adding to such a map copies the new images in; removing
retires them like the replaced submap files (deleted by the next edit). A map built from a
folder of images records that folder's pictures (``source_images``): the record follows every
edit (:func:`~vlm_vpr_ros.maps.map_images.edit_source_index`), so a picture added under a
removed reference's name is never read as the old one.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.errors import (ConfigError, DataError, DescriptorError, ImageDecodeError,
                                MapError)
from vlm_vpr_ros.files.csvio import read_file_column
from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.geodesy import haversine_km, spherical_mean
from vlm_vpr_ros.mapping.assemble import new_index
from vlm_vpr_ros.mapping.local_features import (calibrate_map, calibrated_conditions,
                                                edit_features, map_extractor)
from vlm_vpr_ros.maps import map_images
from vlm_vpr_ros.maps.features import FeatureStore
from vlm_vpr_ros.maps.indexes import effective_kind, make_index, measure_recall
from vlm_vpr_ros.maps.map_images import IMAGES_DIR, image_index, safe_rel, write_image_index
from vlm_vpr_ros.maps.partition import country_codes, partition_kmeans
from vlm_vpr_ros.maps.reference_map import ReferenceMap, descriptor_for_map
from vlm_vpr_ros.maps.submap import Submap, submap_radius_km
from vlm_vpr_ros.maps.transaction import Transaction, edit_lock, finish_manifest

log = logging.getLogger(__name__)

#: a reference fits a K-means submap within this multiple of the submap's radius ...
FIT_SLACK = 1.5
#: ... and always within this distance of its centroid (metres)
FIT_FLOOR_M = 100.0
CHUNK = 64


@dataclass
class EditResult:
    map_dir: Path
    operation: str  # "add" or "remove"
    generation: int
    n_references: int
    n_submaps: int
    changed: list[str] = field(default_factory=list)  # submaps rewritten
    created: list[str] = field(default_factory=list)  # submaps new in this edit
    dropped: list[str] = field(default_factory=list)  # submaps emptied by a removal
    count: int = 0  # references added or removed
    skipped: list[str] = field(default_factory=list)  # unreadable images (add)

    def describe(self) -> str:
        verb = "added" if self.operation == "add" else "removed"
        parts = [f"map {self.map_dir}: {self.count} references {verb}, now "
                 f"{self.n_references} in {self.n_submaps} submaps (generation "
                 f"{self.generation}); rewrote {len(self.changed)} submap(s)"]
        if self.created:
            parts.append(f"new submaps {', '.join(self.created)}")
        if self.dropped:
            parts.append(f"emptied submaps dropped {', '.join(self.dropped)}")
        if self.skipped:
            parts.append(f"{len(self.skipped)} unreadable image(s) skipped")
        return "; ".join(parts)


# -- where new references go ---------------------------------------------------------------------
def _next_kmeans_ids(existing: Iterable[str], n: int) -> list[str]:
    nums = [int(s[1:]) for s in existing if s[:1] == "k" and s[1:].isdigit()]
    start = max(nums, default=-1) + 1
    return [f"k{start + i:03d}" for i in range(n)]


def assign_submaps(ref_map: ReferenceMap, coords: np.ndarray, seed: int = 0) -> list[str]:
    """The submap id each new reference joins (an existing id, or a new one when none fits)."""
    lat, lon = coords[:, 0], coords[:, 1]
    method = ref_map.partition_method
    if method == "none":
        return [ref_map.submaps[0].id] * len(coords)
    if method == "country":
        return country_codes(lat, lon)
    if method != "kmeans":
        raise MapError(f"cannot add to a map partitioned by {method!r}")
    cents = ref_map.centroids
    radius = np.array([max(FIT_SLACK * submap_radius_km(s), FIT_FLOOR_M / 1000.0)
                       for s in ref_map.submaps])
    out: list[str | None] = []
    for a, b in zip(lat, lon):
        d = np.atleast_1d(haversine_km(a, b, cents[:, 0], cents[:, 1]))
        k = int(np.argmin(d))
        out.append(ref_map.submaps[k].id if d[k] <= radius[k] else None)
    left = [i for i, s in enumerate(out) if s is None]
    if left:
        size = max(1, int(np.median([s.count for s in ref_map.submaps])))
        part = partition_kmeans(lat[left], lon[left], math.ceil(len(left) / size), seed)
        names = _next_kmeans_ids((s.id for s in ref_map.submaps), len(part.names))
        for i, lab in zip(left, part.labels):
            out[i] = names[int(lab)]
        log.info("%d new reference(s) fit no submap: %d new submap(s) %s", len(left),
                 len(names), ", ".join(names))
    return [str(s) for s in out]


# -- add ------------------------------------------------------------------------------------------
def _describe(refx, root: Path, rows: Sequence[tuple[str, float, float]],
              progress: bool) -> tuple[np.ndarray, list[int], list[str], list]:
    """Global descriptors, rows read, rows skipped and local features (empty when the map
    stores none) of the references to add."""
    feats, good, skipped, local = [], [], [], []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(rows), desc="describe", unit="img", disable=None, leave=False)
    for s in range(0, len(rows), CHUNK):
        images, idx = [], []
        for i in range(s, min(len(rows), s + CHUNK)):
            try:
                images.append(load_image(root / rows[i][0]))
                idx.append(i)
            except ImageDecodeError as exc:
                log.warning("skipping reference: %s", exc)
                skipped.append(rows[i][0])
        if images:
            g, lf = refx.describe(images)
            feats.append(np.asarray(g, np.float32))
            local += lf or []
            good += idx
        if bar is not None:
            bar.update(min(len(rows), s + CHUNK) - s)
    if bar is not None:
        bar.close()
    dim = refx.descriptor.dim
    return ((np.concatenate(feats) if feats else np.zeros((0, dim), np.float32)), good, skipped,
            local)


def _vectors(sub: Any) -> np.ndarray:
    """All descriptors of a submap, float32 (flat/fp16: from the index; pq: its fp16 re-rank
    vectors)."""
    fn = getattr(sub, "vectors", None)
    if fn is not None:
        return np.asarray(fn(), dtype=np.float32)
    return sub.index.reconstruct_n(0, sub.index.ntotal)


def _kind_of(ref_map: ReferenceMap, sub: Any | None) -> str:
    kind = getattr(sub, "kind", None) if sub is not None else None
    if kind:
        return kind
    kind = ref_map.manifest.get("index", "flat")
    if kind not in ("flat", "fp16", "pq"):  # "auto": new submaps are small
        kinds = {getattr(s, "kind", "flat") for s in ref_map.submaps}
        kind = "fp16" if "fp16" in kinds else "flat"
    return kind


def _rebuilt(ref_map: ReferenceMap, sub_id: str, vectors: np.ndarray, coords: np.ndarray,
             ids: list[str], like: Any | None = None) -> Submap:
    """A submap of the same index kind as ``like`` (or the map's) holding ``vectors``."""
    vecs = np.ascontiguousarray(vectors, dtype=np.float32)
    coords = np.asarray(coords, np.float64)
    centroid = spherical_mean(coords[:, 0], coords[:, 1])
    kind = _kind_of(ref_map, like)
    if kind == "pq" or int(ref_map.manifest.get("version", 1)) >= 2:
        kind = effective_kind(kind, len(vecs))
        trained = _pq_codebook(ref_map) if kind == "pq" else None
        index = make_index(kind, vecs, trained)
        rerank = vecs.astype(np.float16) if kind == "pq" else None
        factor = int(getattr(ref_map, "rerank_factor", 16))
        recall = measure_recall(index, kind, rerank, vecs, factor) if kind != "flat" else None
        return Submap(sub_id, centroid, coords, list(ids), index, kind=kind, rerank=rerank,
                      group=getattr(like, "group", "") if like is not None else "",
                      recall=recall)

    index = new_index(kind, vecs.shape[1])
    index.add(vecs)
    return Submap(sub_id, centroid, coords, list(ids), index)


def _pq_codebook(ref_map: ReferenceMap) -> Any:
    """The map's shared PQ codebook (trained, empty), taken from one of its pq submaps; new
    pq submaps must use it (a new codebook would make distances incomparable)."""
    import faiss

    for s in ref_map.submaps:
        if getattr(s, "kind", "") == "pq":
            index = faiss.clone_index(s.index)
            index.reset()
            return index
    raise MapError("the map has no pq submap to take the PQ codebook from")


def add_references(map_dir: str | os.PathLike[str], images_dir: str | os.PathLike[str],
                   rows: Sequence[tuple[str, float, float]], descriptor: str | None = None,
                   descriptor_config: Mapping[str, Any] | None = None,
                   store_images: bool | None = None, move_images: bool = False,
                   source: Mapping[str, Any] | None = None, progress: bool = True,
                   seed: int = 0) -> EditResult:
    """Describe ``rows`` (``file, lat, lon``; files relative to ``images_dir``) with the map's
    own descriptor and state and add them. ``descriptor``: the name the caller expects (a map
    built with another one is refused). ``store_images``: copy the images into the map
    (default: when the map already holds its images)."""
    path, root = Path(map_dir), Path(images_dir)
    if not rows:
        raise DataError("nothing to add: no references given")
    with edit_lock(path, "map add"):
        ref_map = ReferenceMap.load(path, verify=True)
        built = ref_map.descriptor_identity.get("config", {})
        other = {k: v for k, v in dict(descriptor_config or {}).items()
                 if k in built and str(built[k]) != str(v)}
        if other:
            raise MapError(f"the map's descriptor was built with "
                           f"{', '.join(f'{k}={built[k]!r}' for k in other)}; new references "
                           f"must be described the same way (refused: "
                           f"{', '.join(f'{k}={v!r}' for k, v in other.items())})")
        desc = descriptor_for_map(ref_map, descriptor, descriptor_config)
        known = set(ref_map.all_ids())
        seen: set[str] = set()
        dup = [f for f, _, _ in rows if f in known or (f in seen or seen.add(f))]
        if dup:
            raise DataError(f"{len(dup)} reference id(s) are already in the map or repeated, "
                            f"e.g. {dup[:3]}; remove them first ('vlm-vpr map remove')")
        manifest = ref_map.manifest
        if store_images is None:
            store_images = bool(manifest.get("images"))
        if store_images:
            for f, _, _ in rows:
                safe_rel(f)
        t0 = time.monotonic()
        refx = map_extractor(ref_map, desc)  # the map's own local features, if it stores any
        store = FeatureStore.open(path, manifest)
        feats, good, skipped, local = _describe(refx, root, rows, progress)
        if not good:
            raise MapError(f"no image could be read among the {len(rows)} references to add")
        coords = np.array([[rows[i][1], rows[i][2]] for i in good], np.float64)
        ids = [rows[i][0] for i in good]
        target = assign_submaps(ref_map, coords, seed)
        gen = int(manifest.get("generation", 0)) + 1
        tx = Transaction(path, manifest)
        res = EditResult(path, "add", gen, 0, 0, count=len(ids), skipped=skipped)
        rewritten: dict[str, list] = {}
        try:
            entries = {e["id"]: e for e in tx.new["submaps"]}
            for sid in sorted(set(target)):
                sel = [i for i, t in enumerate(target) if t == sid]
                k = ref_map.submap_index(sid)
                if store is not None:
                    old_lf = [] if k is None else [store.get(sid, j)
                                                   for j in range(ref_map.submaps[k].count)]
                    rewritten[sid] = old_lf + [local[i] for i in sel]
                if k is None:
                    sub = _rebuilt(ref_map, sid, feats[sel], coords[sel],
                                   [ids[i] for i in sel])
                    res.created.append(sid)
                else:
                    old = ref_map.submaps[k]
                    sub = _rebuilt(ref_map, sid, np.concatenate([_vectors(old), feats[sel]]),
                                   np.concatenate([np.asarray(old.coords), coords[sel]]),
                                   list(old.ids) + [ids[i] for i in sel], like=old)
                    for r in entries[sid]["files"].values():
                        tx.new["files"].pop(r, None)
                res.changed.append(sid)
                entries[sid] = tx.write_submap(sub, gen)
            if store_images:
                map_images.store_images(tx, root, ids, image_index(path, manifest), gen,
                                        move_images)
            map_images.edit_source_index(tx, gen, added=ids,
                                         added_from=None if store_images else root)
            edit_features(tx, ref_map, gen, rewritten, [])
            finish_manifest(tx.new, list(entries.values()), gen, "add", len(ids), source)
            tx.commit()
        except BaseException:
            tx.rollback()
            raise
        recalibrate(path, store)
        res.n_references, res.n_submaps = tx.new["n_references"], tx.new["n_submaps"]
        log.info("%s (%.1f s)", res.describe(), time.monotonic() - t0)
        return res


def recalibrate(path: Path, store: Any) -> None:
    """After a committed edit of a map with local features: its leave-one-out calibration of
    p_correct again (the look-alikes of the map changed; docs/verification.md), under the
    query conditions it was calibrated for (the default ones when it records none). When those
    need the reference pictures and they are not reachable, the earlier calibration is kept
    (a WARN says how to recalibrate), never replaced by a full-size-only one."""
    if store is None:
        return
    try:
        ref_map = ReferenceMap.load(path, verify=False)
        conditions = calibrated_conditions(ref_map)
        need = [c for c in conditions or () if c != "full"]
        why = need and map_images.pictures_problem(path, ref_map.manifest, ref_map.all_ids())
        if why:  # a full-size-only calibration would silently replace the one it has
            log.warning("%s: p_correct keeps its earlier calibration: conditions %s need the "
                        "reference pictures: %s; recalibrate with 'vlm-vpr calibrate --map "
                        "%s --conditions %s --reference-images DIR'", path, ",".join(need),
                        why, path, ",".join(conditions))
            return
        calibrate_map(ref_map, conditions=conditions)
    except (ConfigError, DescriptorError) as exc:  # e.g. learned weights not at hand here
        log.warning("%s: p_correct keeps its earlier calibration (%s); recalibrate where the "
                    "matcher's weights are", path, exc)


# -- remove ---------------------------------------------------------------------------------------
def read_ids_file(path: str | os.PathLike[str]) -> list[str]:
    """Reference ids to remove: one per line (``#`` comments and blank lines ignored), or a
    CSV with a ``file`` column (e.g. a coordinates CSV)."""
    p = Path(path)
    if p.suffix.lower() == ".csv":
        ids = read_file_column(p)
    else:
        try:
            text = p.read_text(encoding="utf-8-sig")
        except (OSError, UnicodeDecodeError) as exc:
            raise DataError(f"cannot read the ids file {p}: {exc}") from None
        ids = [ln.strip() for ln in text.splitlines() if ln.strip() and
               not ln.lstrip().startswith("#")]
    if not ids:
        raise DataError(f"{p}: no reference ids")
    return ids


def remove_references(map_dir: str | os.PathLike[str], ids: Iterable[str],
                      source: Mapping[str, Any] | None = None) -> EditResult:
    """Remove references by id; unknown ids are an error (nothing is changed)."""
    path = Path(map_dir)
    drop = set(ids)
    with edit_lock(path, "map remove"):
        ref_map = ReferenceMap.load(path, verify=True)
        unknown = sorted(drop - set(ref_map.all_ids()))
        if unknown:
            raise DataError(f"{len(unknown)} id(s) are not in the map {path}, e.g. "
                            f"{unknown[:3]}; nothing was removed")
        if len(drop) >= ref_map.n_references:
            raise MapError(f"removing all {ref_map.n_references} references would leave an "
                           "empty map; build a new map instead")
        manifest = ref_map.manifest
        gen = int(manifest.get("generation", 0)) + 1
        tx = Transaction(path, manifest)
        res = EditResult(path, "remove", gen, 0, 0, count=len(drop))
        store = FeatureStore.open(path, manifest)
        rewritten: dict[str, list] = {}
        try:
            entries = {e["id"]: e for e in tx.new["submaps"]}
            for sub in ref_map.submaps:
                keep = [j for j, i in enumerate(list(sub.ids)) if i not in drop]
                if len(keep) == sub.count:
                    continue
                for r in entries[sub.id]["files"].values():
                    tx.new["files"].pop(r, None)
                if not keep:
                    del entries[sub.id]
                    res.dropped.append(sub.id)
                    continue
                new = _rebuilt(ref_map, sub.id, _vectors(sub)[keep],
                               np.asarray(sub.coords)[keep], [sub.ids[j] for j in keep],
                               like=sub)
                if store is not None:
                    rewritten[sub.id] = [store.get(sub.id, j) for j in keep]
                entries[sub.id] = tx.write_submap(new, gen)
                res.changed.append(sub.id)
            index = image_index(path, manifest)
            stored = [i for i in drop if i in index]
            if stored:
                for i in stored:
                    del index[i]
                    tx.retire(f"{IMAGES_DIR}/{i}")
                write_image_index(tx, index, gen)
            map_images.edit_source_index(tx, gen, removed=sorted(drop))
            edit_features(tx, ref_map, gen, rewritten, res.dropped)
            finish_manifest(tx.new, list(entries.values()), gen, "remove", len(drop), source)
            tx.commit()
        except BaseException:
            tx.rollback()
            raise
        recalibrate(path, store)  # the removed images are ``retired`` (the next edit deletes)
        res.n_references, res.n_submaps = tx.new["n_references"], tx.new["n_submaps"]
        log.info("%s", res.describe())
        return res
