"""The map: a folder with a versioned manifest, opened as a :class:`ReferenceMap`.

:meth:`ReferenceMap.load` reads the manifest, checks it (:mod:`vlm_vpr_ros.maps.format`) and
opens format version 2 memory-mapped and lazily (:mod:`vlm_vpr_ros.maps.store`) or version 1
into memory (:mod:`vlm_vpr_ros.maps.v1`). Maps are built by :mod:`vlm_vpr_ros.mapping.build_images`
(images), :mod:`vlm_vpr_ros.mapping.build_descriptors` (precomputed descriptors) and
:mod:`vlm_vpr_ros.bags.teach` (a robot's bag), and edited by :mod:`vlm_vpr_ros.mapping.edit`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.descriptors import GlobalDescriptor, create_descriptor
from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.maps import indexes, store, v1
from vlm_vpr_ros.maps.format import check_descriptor_identity, load_state, read_manifest
from vlm_vpr_ros.maps.search import Hits, SmallSubmaps, SubmapPass, unique_ints
from vlm_vpr_ros.maps.submap import Submap

log = logging.getLogger(__name__)

#: read-ahead advice for the hits' coords and ids only on maps where those files are this big:
#: smaller ones stay in the page cache after the first queries, and the advice (an open, a
#: fadvise per row and a close per file) then costs ~0.5 ms per query for nothing
PREFETCH_MIN_BYTES = 64 * 2 ** 20
HIT_ROLES = ("coords", "ids")  # the files of a submap read for its hits ...
POOLED_ROLES = ("index", "coords", "ids")  # ... and, for a pooled submap, its index file


class ReferenceMap:
    """A loaded (or freshly built) map. Use :meth:`load`; build with
    :func:`vlm_vpr_ros.mapping.build_images.build_map` (module docstring)."""

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
        self._small: SmallSubmaps | None = None  # see small_submaps()
        self._cache: dict = {}  # row_bytes()
        self._small_lock = threading.Lock()
        self._hits_checked: tuple[tuple, set[int]] = ((None, None), set())  # rank_submaps
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

    def search_submaps(self, submaps: list[int], q: np.ndarray, k: int,
                       with_global: bool = False) -> list[tuple[float, int, int]]:
        """Top-``k`` (squared L2, submap, row) over several submaps, best first (ties by
        submap, row): :meth:`rank_submaps` as a list of tuples."""
        dist, sub, row = self.rank_submaps(submaps, q, k, with_global)
        return list(zip(dist.tolist(), sub.tolist(), row.tolist()))

    def rank_submaps(self, submaps: list[int], q: np.ndarray, k: int,
                     with_global: bool = False) -> Hits:
        """Top-``k`` hits over several submaps as arrays (squared L2 float32, submap, row),
        best first (ties by submap, row). flat/fp16 submaps are searched exactly, one by one;
        pq submaps together, as one pq index over their union would be: PQ candidates from
        each (serially: threads measured slower, OpenMP teams contend), then only the best
        ``k·rerank_factor`` of them all are re-ranked exactly (one re-rank per query, not one
        per submap).

        ``with_global``: also the map's global top-``k`` hits that the ranking of ``submaps``
        lacks, merged in by distance (``submaps``' hits first on ties): the posterior fusion's
        region + global merge, from one pass in which no submap is searched twice
        (:mod:`vlm_vpr_ros.maps.search`)."""
        small = self.small_submaps()
        watch = getattr(self.submaps[0], "watch", None) if self.submaps else None
        with watch.query() if watch is not None else contextlib.nullcontext():
            sweep = SubmapPass(self.submaps, q, k, self.rerank_factor, small)
            dist, sub, row = sweep.rank_with_global(submaps) if with_global else \
                sweep.rank(submaps)[0]
            touched = unique_ints(sub).tolist()
            advise = (len(touched) > 1
                      and self.row_bytes(("coords", "ids")) >= PREFETCH_MIN_BYTES)
            # submaps whose hits' files passed in this change-notice generation (a query
            # touches ~20 submaps: a call each cost ~90 us right after the scans, issue 31);
            # without a change notice, every query checks them all
            gen = watch.current() if watch is not None else None
            memo = self._hits_checked
            if gen is None or memo[0] != (gen, small):
                memo = self._hits_checked = ((gen, small), set())
            for si in touched:  # the caller reads the hits' ids and positions next; a pooled
                # submap's hits came from its copy in RAM: its index file is checked here too,
                # so a submap changed on disk fails the queries it answers (maps/store.py)
                if si not in memo[1]:
                    self.submaps[si].check_files(POOLED_ROLES if small.pooled[si]
                                                 else HIT_ROLES)
                    memo[1].add(si)
                if advise:  # cold pages of several files: reads queued at once
                    self.submaps[si].prefetch(np.sort(row[sub == si]), ("coords", "ids"))
        return dist, sub, row

    def row_bytes(self, roles: tuple[str, ...]) -> int:
        """Bytes on disk of the submaps' files in ``roles`` (v2 manifest; 0 in memory)."""
        key = ("row_bytes", roles)
        if key not in self._cache:
            files = self.manifest.get("files") or {}
            self._cache[key] = sum(int((files.get(rel) or {}).get("bytes", 0))
                                   for entry in self.manifest.get("submaps", [])
                                   if isinstance(entry, dict)
                                   for role, rel in (entry.get("files") or {}).items()
                                   if role in roles)
        return self._cache[key]

    def small_submaps(self) -> SmallSubmaps:
        """The small submaps' pooled copy (built on the first search, :mod:`.search`)."""
        small = self._small
        if small is None or small.source != tuple(map(id, self.submaps)):
            with self._small_lock:
                small = self._small
                if small is None or small.source != tuple(map(id, self.submaps)):
                    small = self._small = SmallSubmaps(self.submaps)
                    log.debug("pooled %d small submaps (%d references) for one-call search",
                              int(small.pooled.sum()), small.n_refs)
        return small

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
