"""The map: a folder with a versioned manifest, opened as a :class:`ReferenceMap`.

:meth:`ReferenceMap.load` reads the manifest, checks it (:mod:`vlm_vpr_ros.maps.format`) and
opens format version 2 memory-mapped and lazily (:mod:`vlm_vpr_ros.maps.store`) or version 1
into memory (:mod:`vlm_vpr_ros.maps.v1`). Maps are built by :mod:`vlm_vpr_ros.maps.build_images`
(images), :mod:`vlm_vpr_ros.maps.build_descriptors` (precomputed descriptors) and
:mod:`vlm_vpr_ros.bags.teach` (a robot's bag), and edited by :mod:`vlm_vpr_ros.maps.edit`.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.descriptors import GlobalDescriptor, create_descriptor
from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.maps import indexes, store, v1
from vlm_vpr_ros.maps.format import check_descriptor_identity, load_state, read_manifest
from vlm_vpr_ros.maps.submap import Submap

log = logging.getLogger(__name__)


class ReferenceMap:
    """A loaded (or freshly built) map. Use :meth:`load`; build with
    :func:`vlm_vpr_ros.maps.build_images.build_map` (module docstring)."""

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
        self.rerank_factor = int(manifest.get("index_params", {}).get(
            "rerank_factor", indexes.DEFAULT_RERANK_FACTOR))

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

    # persistence
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the map folder (format v2) atomically: files first, manifest last."""
        path = Path(path)
        self.manifest, self.path = store.save_map(self, path), path

    def save_v1(self, path: str | os.PathLike[str]) -> None:
        """Write format version 1 (flat/fp16 only): kept for compatibility tests and tools."""
        v1.save_v1(self, path)

    @classmethod
    def load(cls, path: str | os.PathLike[str], verify: bool = False) -> "ReferenceMap":
        """Open and validate a map folder; any inconsistency raises MapError saying what.
        v2: manifest + file sizes only, submaps memory-mapped on first use; ``verify`` adds the
        full sha256 pass (``vlm-vpr map verify``). v1: read into memory (checksums with
        ``verify``)."""
        path = Path(path)
        manifest = read_manifest(path)
        if manifest["version"] >= 2:
            m = cls(manifest, *store.open_submaps(path, manifest, verify), path)
            log.info("opened map %s: %d references in %d submaps (%s, %s-D, index %s)", path,
                     m.n_references, len(m.submaps), manifest["partition"]["method"],
                     manifest["descriptor"]["dim"], manifest.get("index"))
            return m
        state = load_state(path, manifest, verify)
        subs = [v1.load_submap(path, manifest, entry, verify) for entry in manifest["submaps"]]
        total = sum(s.count for s in subs)
        if total != manifest["n_references"]:
            raise MapError(f"{path}: submaps hold {total} references, manifest says "
                           f"{manifest['n_references']}")
        log.info("loaded map %s: %d references in %d submaps (%s, %s-D)", path, total,
                 len(subs), manifest["partition"]["method"], manifest["descriptor"]["dim"])
        return cls(manifest, subs, state, path)



def descriptor_for_map(ref_map: ReferenceMap, expect: str | None = None,
                       options: Mapping[str, Any] | None = None) -> GlobalDescriptor:
    """Create the query-time descriptor of a map (its stored config + ``options`` such as
    ``weights``/``device``) and check it is the same as the map's."""
    ident = ref_map.descriptor_identity
    if expect and expect != ident["name"]:
        raise MapError(f"the map at {ref_map.path} was built with descriptor "
                       f"{ident['name']!r}, but {expect!r} was requested")
    desc = create_descriptor(ident["name"], {**ident.get("config", {}), **dict(options or {})})
    if ref_map.descriptor_state:
        desc.load_state(ref_map.descriptor_state)
    query_ident = desc.identity()
    check_descriptor_identity(ident, query_ident)
    built, now = ident.get("weights_sha256"), query_ident.get("weights_sha256")
    if built and now and built != now:
        log.warning("the map was built with another checkpoint of %s (sha256 %s..., now %s...):"
                    " descriptors may not be comparable", ident["name"], built[:12], now[:12])
    return desc
