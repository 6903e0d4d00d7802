"""The map folder: versioned ``manifest.json`` + per-submap FAISS indices, coordinates and ids.

New maps are written in format version 2 (memory-mapped, lazily opened submaps, index kinds
flat/fp16/pq): see :mod:`vlm_vpr_ros.maps.store` and docs/planet_scale.md. Version 1 (below)
still loads (fully into memory); ``vlm-vpr map upgrade`` converts it.

Version 1 layout::

    MAP/manifest.json              format, version, descriptor identity, metric, partition, counts,
                                   submap centroids, size + sha256 of every file
    MAP/descriptor_state.npz       fitted descriptor state (codebook, PCA), if any (no pickle)
    MAP/submaps/<id>.faiss         exact L2 FAISS index of the submap's descriptors (IndexFlatL2,
                                   or fp16 IndexScalarQuantizer with ``--index fp16``)
    MAP/submaps/<id>.coords.npy    (n, 2) float64 lat/lon
    MAP/submaps/<id>.ids.json      reference ids (image paths relative to the images folder)

Every file is written to a temporary name and moved into place with ``os.replace``; the manifest
is written last, so a folder with a manifest is always complete.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros import __version__
from vlm_vpr_ros.errors import MapError, OutputError

log = logging.getLogger(__name__)

MAP_FORMAT = "vlm_vpr_ros.map"
MAP_VERSION = 2  # written; see maps/store.py
SUPPORTED_VERSIONS = (1, 2)
METRIC = "squared_l2"
MANIFEST = "manifest.json"
#: identity keys that must agree between a map and the query-time descriptor
IDENTITY_KEYS = ("name", "dim", "release", "preprocessing")


# -- atomic file helpers ----------------------------------------------------------------------
def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write through ``.NAME.tmpPID`` + ``os.replace``; on any OS error (disk full, no
    permission) the temporary file is removed and an OutputError says what happened."""
    from vlm_vpr_ros.outputs import describe_os_error

    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OutputError):
            raise
        raise OutputError(describe_os_error(exc, path)) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=False) + "\n").encode())


def atomic_save_npy(path: Path, arr: np.ndarray) -> None:
    import io

    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(arr), allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())


def atomic_save_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    import io

    buf = io.BytesIO()
    np.savez(buf, **{k: np.ascontiguousarray(v) for k, v in arrays.items()})
    atomic_write_bytes(path, buf.getvalue())


def atomic_write_index(path: Path, index: Any) -> None:
    import faiss

    atomic_write_bytes(path, faiss.serialize_index(index).tobytes())


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# -- the in-memory map ------------------------------------------------------------------------
@dataclass
class Submap:
    """An in-memory submap (built now, or loaded from a v1 map). v2 maps load as
    :class:`vlm_vpr_ros.maps.store.LazySubmap`, which has the same attributes and methods."""

    id: str
    centroid: tuple[float, float]
    coords: np.ndarray  # (n, 2) float64
    ids: list[str]
    index: Any  # faiss.IndexFlatL2, fp16 IndexScalarQuantizer or IndexPQFastScan
    kind: str = "flat"  # flat | fp16 | pq (maps/indexes.py)
    rerank: np.ndarray | None = None  # pq: (n, dim) float16 re-rank vectors
    group: str = ""  # the submap this one was split from (balanced submaps); "" = itself
    recall: dict | None = None  # measured recall vs exact (approximate kinds)

    @property
    def count(self) -> int:
        return len(self.ids)

    def search(self, q: np.ndarray, k: int, factor: int) -> tuple[np.ndarray, np.ndarray]:
        from vlm_vpr_ros.maps.indexes import search

        return search(self.index, self.kind, self.rerank, q, k, factor)

    def pq_candidates(self, q: np.ndarray, kk: int) -> tuple[np.ndarray, np.ndarray]:
        from vlm_vpr_ros.maps.indexes import pq_candidates

        return pq_candidates(self.index, q, kk)

    def exact_sq_l2(self, rows: np.ndarray, q: np.ndarray) -> np.ndarray:
        from vlm_vpr_ros.maps.indexes import exact_sq_l2

        return exact_sq_l2(self.rerank, rows, q)

    def prefetch(self, rows: np.ndarray, what: tuple[str, ...]) -> None:
        """In memory: nothing to read ahead (see ``LazySubmap.prefetch``)."""

    def vectors(self) -> np.ndarray:
        from vlm_vpr_ros.maps.indexes import vectors

        return vectors(self.index, self.kind, self.rerank)


def submap_radius_km(sub: Any) -> float:
    """Largest distance (km) from a submap's centroid to one of its references: stored in v2
    manifests (so opening a map reads no coordinates), computed for older maps."""
    stored = getattr(sub, "radius_km", None)
    if stored is not None:
        return float(stored)
    from vlm_vpr_ros.geodesy import farthest_km

    return farthest_km(sub.centroid[0], sub.centroid[1], sub.coords) if sub.count else 0.0


class ReferenceMap:
    """A loaded (or freshly built) map. Use :meth:`load`; build with ``map_build.build_map``."""

    def __init__(self, manifest: dict, submaps: list[Submap],
                 descriptor_state: dict[str, np.ndarray], path: Path | None = None) -> None:
        self.manifest = manifest
        self.submaps = submaps
        self.descriptor_state = descriptor_state
        self.path = path
        self._by_id = {s.id: i for i, s in enumerate(submaps)}
        self._groups: dict[str, list[int]] = {}
        for i, s in enumerate(submaps):
            self._groups.setdefault(s.group or s.id, []).append(i)
        #: pq submaps re-rank the top k·rerank_factor PQ candidates exactly (tunable per query)
        self.rerank_factor = int(manifest.get("index_params", {}).get("rerank_factor", 16))

    # properties
    @property
    def dim(self) -> int:
        return int(self.manifest["descriptor"]["dim"])

    @property
    def descriptor_identity(self) -> dict:
        return self.manifest["descriptor"]

    @property
    def partition_method(self) -> str:
        return self.manifest["partition"]["method"]

    @property
    def n_references(self) -> int:
        return sum(s.count for s in self.submaps)

    @property
    def centroids(self) -> np.ndarray:
        return np.array([s.centroid for s in self.submaps], dtype=np.float64).reshape(-1, 2)

    def submap_index(self, submap_id: str) -> int | None:
        return self._by_id.get(submap_id)

    def group_members(self, group: str) -> list[int]:
        """Indices of the submaps a (country / cluster) group was split into (balanced maps);
        ``[i]`` for an unsplit submap, ``[]`` when there is no such group."""
        return list(self._groups.get(group, []))

    def search_submap(self, i: int, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-``k`` (squared L2, row) in submap ``i`` for a (1, dim) float32 query."""
        return self.submaps[i].search(q, k, self.rerank_factor)

    def open_submaps(self) -> "ReferenceMap":
        """Open and check every submap now (v2 maps open them lazily, on first search). Batch
        tools call this so a damaged map fails before the first query, naming the file; the
        node does not (it starts in about a second at 4.1M references and reports a damaged
        submap on the queries that reach it)."""
        t0 = time.perf_counter()
        for s in self.submaps:
            opened = getattr(s, "opened", None)
            if opened is not None:
                opened()
        log.debug("opened %d submaps in %.2f s", len(self.submaps), time.perf_counter() - t0)
        return self

    def search_submaps(self, submaps: list[int], q: np.ndarray,
                       k: int) -> list[tuple[float, int, int]]:
        """Top-``k`` (squared L2, submap, row) over several submaps, best first (ties by
        submap, row). flat/fp16 submaps are searched exactly, one by one; pq submaps together,
        as one pq index over their union would be: PQ candidates from each (serially: threads
        measured slower, OpenMP teams contend), then only the best ``k·rerank_factor`` of them
        all are re-ranked exactly (one re-rank per query, not one per submap)."""
        found: list[tuple[float, int, int]] = []
        live = [si for si in submaps if self.submaps[si].count > 0]
        pq = [si for si in live if self.submaps[si].kind == "pq"] if len(live) > 1 else []
        for si in live:
            if si not in pq:
                dist, idx = self.search_submap(si, q, min(k, self.submaps[si].count))
                found += [(float(d), si, int(j)) for d, j in zip(dist, idx) if j >= 0]
        if pq:
            kk = k * max(1, self.rerank_factor)
            stage1 = [self.submaps[si].pq_candidates(q, kk) for si in pq]
            approx = np.concatenate([d for d, _ in stage1])
            owner = np.concatenate([np.full(len(r), si) for si, (_, r) in zip(pq, stage1)])
            rows = np.concatenate([r for _, r in stage1])
            if len(approx) > kk:
                best = np.argpartition(approx, kk - 1)[:kk]
                owner, rows = owner[best], rows[best]
            picked = [(si, np.sort(rows[owner == si])) for si in np.unique(owner).tolist()]
            if len(picked) > 1:  # cold pages of many files: all reads queued at once (one
                for si, r in picked:  # submap: measured no gain, only the advice's cost)
                    self.submaps[si].prefetch(r, ("vectors",))
            for si, r in picked:
                dist = self.submaps[si].exact_sq_l2(r, q)
                found += [(float(d), si, int(j)) for d, j in zip(dist, r)]
        found.sort()
        found = found[:k]
        by_sub: dict[int, list[int]] = {}
        for _, si, j in found:  # the caller reads their ids and positions next
            by_sub.setdefault(si, []).append(j)
        for si, r in by_sub.items() if len(by_sub) > 1 else ():
            self.submaps[si].prefetch(np.sort(np.array(r)), ("coords", "ids"))
        return found

    def all_descriptors(self) -> np.ndarray:
        """All descriptors (submap order): reconstructed from flat/fp16 indices, or the fp16
        re-rank vectors of pq submaps."""
        return np.concatenate([s.vectors() for s in self.submaps])

    def all_coords(self) -> np.ndarray:
        return np.concatenate([s.coords for s in self.submaps])

    def all_ids(self) -> list[str]:
        return [i for s in self.submaps for i in s.ids]

    def with_partition(self, method: str, clusters: int = 100, seed: int = 0) -> "ReferenceMap":
        """The same references and descriptors, re-partitioned in memory (for ablations)."""
        from vlm_vpr_ros.map_build import assemble_map

        coords = self.all_coords()
        return assemble_map(self.all_descriptors(), coords, self.all_ids(),
                            dict(self.manifest["descriptor"]), self.descriptor_state,
                            method, clusters, seed, extra=self.manifest.get("source", {}),
                            index=_single_kind(self))

    # persistence
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the map folder (format v2) atomically: files first, manifest last."""
        from vlm_vpr_ros.maps.store import save_map

        path = Path(path)
        self.manifest, self.path = save_map(self, path), path

    def save_v1(self, path: str | os.PathLike[str]) -> None:
        """Write format version 1 (flat/fp16 only): kept for compatibility tests and tools."""
        path = Path(path)
        (path / "submaps").mkdir(parents=True, exist_ok=True)
        files: dict[str, dict] = {}
        if self.descriptor_state:
            atomic_save_npz(path / "descriptor_state.npz", self.descriptor_state)
            files["descriptor_state.npz"] = {}
        subs = []
        for s in self.submaps:
            rel = {"index": f"submaps/{s.id}.faiss", "coords": f"submaps/{s.id}.coords.npy",
                   "ids": f"submaps/{s.id}.ids.json"}
            atomic_write_index(path / rel["index"], s.index)
            atomic_save_npy(path / rel["coords"], np.asarray(s.coords, dtype=np.float64))
            atomic_write_json(path / rel["ids"], list(s.ids))
            files.update({v: {} for v in rel.values()})
            subs.append({"id": s.id, "count": s.count,
                         "centroid": [round(float(c), 7) for c in s.centroid], "files": rel})
        for rel in files:
            p = path / rel
            files[rel] = {"bytes": p.stat().st_size, "sha256": sha256_file(p)}
        manifest = dict(self.manifest)
        manifest.update({
            "format": MAP_FORMAT, "version": 1, "software": f"vlm_vpr_ros {__version__}",
            "metric": METRIC, "n_references": self.n_references, "n_submaps": len(subs),
            "descriptor_state": "descriptor_state.npz" if self.descriptor_state else None,
            "submaps": subs, "files": files,
        })
        atomic_write_json(path / MANIFEST, manifest)

    @classmethod
    def load(cls, path: str | os.PathLike[str], verify: bool = False) -> "ReferenceMap":
        """Open and validate a map folder; any inconsistency raises MapError saying what.
        v2: manifest + file sizes only, submaps memory-mapped on first use; ``verify`` adds the
        full sha256 pass (``vlm-vpr map verify``). v1: read into memory (checksums with
        ``verify``)."""
        from vlm_vpr_ros.map_validate import read_manifest, load_submap, load_state

        path = Path(path)
        manifest = read_manifest(path)
        if manifest["version"] >= 2:
            from vlm_vpr_ros.maps.store import load_map

            m = load_map(path, manifest, verify)
            log.info("opened map %s: %d references in %d submaps (%s, %s-D, index %s)", path,
                     m.n_references, len(m.submaps), manifest["partition"]["method"],
                     manifest["descriptor"]["dim"], manifest.get("index"))
            return m
        state = load_state(path, manifest, verify)
        subs = [load_submap(path, manifest, entry, verify) for entry in manifest["submaps"]]
        total = sum(s.count for s in subs)
        if total != manifest["n_references"]:
            raise MapError(f"{path}: submaps hold {total} references, manifest says "
                           f"{manifest['n_references']}")
        log.info("loaded map %s: %d references in %d submaps (%s, %s-D)", path, total,
                 len(subs), manifest["partition"]["method"], manifest["descriptor"]["dim"])
        return cls(manifest, subs, state, path)


def _single_kind(m: "ReferenceMap") -> str:
    kinds = {getattr(s, "kind", "flat") for s in m.submaps}
    return kinds.pop() if len(kinds) == 1 else "fp16"


def check_descriptor_identity(map_identity: Mapping[str, Any],
                              query_identity: Mapping[str, Any]) -> None:
    """Raise MapError when a query-time descriptor would not be comparable with the map's."""
    diffs = [k for k in IDENTITY_KEYS
             if map_identity.get(k) != query_identity.get(k)]
    if diffs:
        detail = "; ".join(f"{k}: map={map_identity.get(k)!r} query={query_identity.get(k)!r}"
                           for k in diffs)
        raise MapError(f"descriptor mismatch between map and query ({detail})")
