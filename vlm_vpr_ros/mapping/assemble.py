"""References + descriptors -> an in-memory :class:`ReferenceMap`: partition, balance, one
FAISS index per submap (every builder ends here; ablations re-partition through it)."""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.mapping.balance import split_large
from vlm_vpr_ros.maps.indexes import (DEFAULT_RERANK_FACTOR, PQ_TRAIN_SAMPLE,
                                      check_kind, choose_kinds, effective_kind, make_index,
                                      measure_recall, train_pq)
from vlm_vpr_ros.maps.partition import make_partition
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.maps.submap import Submap


def assemble_map(desc: np.ndarray, coords: np.ndarray, ids: list[str], identity: dict,
                 state: Mapping[str, np.ndarray], partition: str, clusters: int = 100,
                 seed: int = 0, extra: Mapping[str, Any] | None = None,
                 index: str = "flat", ram_budget_mb: float | None = None,
                 max_submap_size: int | None = None,
                 rerank_factor: int = DEFAULT_RERANK_FACTOR, engine: Any = None) -> ReferenceMap:
    """Partition references and build one index per submap (in memory).
    ``index``: "flat" (float32, exact), "fp16" (exact on fp16-rounded descriptors), "pq"
    (PQ fast-scan + exact fp16 re-rank) or "auto" (per submap within ``ram_budget_mb``); see
    maps/indexes.py. ``max_submap_size`` splits larger submaps (mapping/balance.py).
    ``engine``: run the partition and the flat/fp16 index builds elsewhere (``partition(...)``,
    ``build_indexes(kind, dim, parts)``; the Ray engine runs them as tasks); pq is built here."""
    check_kind(index)
    part = (engine.partition if engine is not None else make_partition)(
        partition, coords[:, 0], coords[:, 1], clusters, seed)
    part, groups = split_large(part, coords[:, 0], coords[:, 1], max_submap_size, seed)
    sels = [np.flatnonzero(part.labels == k) for k in range(len(part.names))]
    kinds = plan_kinds(index, [len(s) for s in sels], desc.shape[1], ram_budget_mb)
    remote = None
    if engine is not None and len(set(kinds)) == 1 and kinds[0] in ("flat", "fp16"):
        remote = engine.build_indexes(kinds[0], desc.shape[1], [desc[sel] for sel in sels])
    trained = None
    if "pq" in kinds:
        rng = np.random.default_rng(seed)
        sample = rng.choice(len(desc), min(len(desc), PQ_TRAIN_SAMPLE), replace=False)
        trained = train_pq(np.asarray(desc[np.sort(sample)], dtype=np.float32))
    submaps = []
    for k, name in enumerate(part.names):
        sel, kind = sels[k], kinds[k]
        vecs = np.ascontiguousarray(desc[sel], dtype=np.float32)
        faiss_index = remote[k] if remote is not None else make_index(kind, vecs, trained)
        rerank = vecs.astype(np.float16) if kind == "pq" else None
        recall = (measure_recall(faiss_index, kind, rerank, vecs, rerank_factor, seed=seed)
                  if kind != "flat" else None)
        submaps.append(Submap(name, tuple(float(c) for c in part.centroids[k]),
                              coords[sel].astype(np.float64), [ids[i] for i in sel],
                              faiss_index, kind=kind, rerank=rerank,
                              group=groups[k] if groups[k] != name else "", recall=recall))
    manifest = {"descriptor": identity, "index": index,
                "index_params": {"rerank_factor": int(rerank_factor),
                                 "ram_budget_mb": ram_budget_mb},
                "partition": {"method": part.method, "params": part.params},
                "source": dict(extra or {})}
    return ReferenceMap(manifest, submaps, dict(state))



def plan_kinds(index: str, counts: list[int], dim: int,
               ram_budget_mb: float | None) -> list[str]:
    """The index kind of every submap for a requested ``index`` (see maps/indexes.py)."""
    if index == "auto":
        return choose_kinds(counts, dim, ram_budget_mb)
    return [effective_kind(index, c) for c in counts]


def new_index(kind: str, dim: int) -> Any:
    """An empty exact L2 index: "flat" = IndexFlatL2, "fp16" = fp16 scalar-quantized."""
    import faiss

    choose(kind, dict.fromkeys(("flat", "fp16")), "index type")
    if kind == "flat":
        return faiss.IndexFlatL2(dim)
    return faiss.IndexScalarQuantizer(dim, faiss.ScalarQuantizer.QT_fp16, faiss.METRIC_L2)


def repartition(ref_map: ReferenceMap, method: str, clusters: int = 100,
                seed: int = 0) -> ReferenceMap:
    """The same references and descriptors, re-partitioned in memory (for ablations)."""
    kinds = {getattr(s, "kind", "flat") for s in ref_map.submaps}
    return assemble_map(ref_map.all_descriptors(), ref_map.all_coords(), ref_map.all_ids(),
                        dict(ref_map.manifest["descriptor"]), ref_map.descriptor_state,
                        method, clusters, seed, extra=ref_map.manifest.get("source", {}),
                        index=kinds.pop() if len(kinds) == 1 else "fp16")
