"""Index kinds of a submap and their search: exact float32, exact fp16, and two-stage PQ.

``flat``  IndexFlatL2: exact float32 (4·dim bytes per reference, memory-mapped).
``fp16``  IndexScalarQuantizer(QT_fp16): exact on fp16-rounded vectors (2·dim bytes, mmap'd).
``pq``    IndexPQFastScan codes in RAM (dim/4 bytes: PQ{dim/2}x4fs) select the top
          ``k·rerank_factor`` references, then the exact squared L2 to their fp16 vectors (a
          memory-mapped ``.f16.npy`` that stays on disk) re-ranks them and keeps the top ``k``.
``auto``  (build option only) picks one of the three per submap from a RAM budget.

One PQ codebook is trained per map on a sample of all references and shared by every pq submap
(training per submap would cost seconds each; the codebook is tiny).
"""

from __future__ import annotations

import functools
import logging
from typing import Any, Sequence

import numpy as np

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.threads import scratch

log = logging.getLogger(__name__)

INDEX_KINDS = ("flat", "fp16", "pq", "auto")
SUBMAP_KINDS = ("flat", "fp16", "pq")
DEFAULT_RERANK_FACTOR = 16  # 8 measured 96-99 % recall@50 on dense clustered data, 16: >= 99 %
#: a pq submap smaller than this is stored fp16 instead (a scan is already cheap there)
PQ_MIN_REFS = 1024
PQ_TRAIN_SAMPLE = 32768


def check_kind(kind: str, allowed: tuple[str, ...] = INDEX_KINDS) -> str:
    return choose(kind, dict.fromkeys(allowed), "index type")


def pq_m(dim: int) -> int:
    """Sub-quantizers of the PQ codes: 2 dimensions each (4 bits) when dim is even."""
    return dim // 2 if dim % 2 == 0 else dim


def pq_factory(dim: int) -> str:
    return f"PQ{pq_m(dim)}x4fs"


def ram_bytes(kind: str, n: int, dim: int) -> int:
    """Bytes a submap keeps hot while it is searched (what ``auto`` budgets and ``map info``
    reports): a flat/fp16 scan touches every vector; pq keeps only its codes in RAM."""
    if kind == "flat":
        return n * dim * 4
    if kind == "fp16":
        return n * dim * 2
    return n * ((pq_m(dim) + 1) // 2)


def disk_bytes(kind: str, n: int, dim: int) -> int:
    """Approximate bytes on disk of a submap's vectors (index + re-rank file)."""
    return {"flat": n * dim * 4, "fp16": n * dim * 2}.get(kind, n * dim * 2 + ram_bytes(
        "pq", n, dim))


def effective_kind(kind: str, n: int) -> str:
    """What a requested kind becomes for a submap of ``n`` references."""
    return "fp16" if kind == "pq" and n < PQ_MIN_REFS else kind


def choose_kinds(counts: list[int], dim: int, budget_mb: float | None) -> list[str]:
    """``auto``: the most exact kind per submap such that the sum of :func:`ram_bytes` fits
    ``budget_mb``; the largest submaps are downgraded first (flat → fp16 → pq)."""
    kinds = ["flat"] * len(counts)
    if budget_mb is None:
        raise MapError("--index auto needs --ram-budget-mb")
    budget = float(budget_mb) * 2 ** 20
    order = sorted(range(len(counts)), key=lambda i: -counts[i])
    for target in ("fp16", "pq"):
        for i in order:
            if sum(ram_bytes(k, c, dim) for k, c in zip(kinds, counts)) <= budget:
                return [effective_kind(k, c) for k, c in zip(kinds, counts)]
            kinds[i] = target
    total = sum(ram_bytes(k, c, dim) for k, c in zip(kinds, counts))
    if total > budget:
        log.warning("auto index: even pq everywhere needs %.0f MB, more than the %.0f MB budget",
                    total / 2 ** 20, budget / 2 ** 20)
    return [effective_kind(k, c) for k, c in zip(kinds, counts)]


def train_pq(sample: np.ndarray) -> Any:
    """A trained, empty PQ fast-scan index (the map's shared codebook)."""
    import faiss

    sample = np.ascontiguousarray(sample, dtype=np.float32)
    index = faiss.index_factory(sample.shape[1], pq_factory(sample.shape[1]))
    # M tiny 16-centroid k-means: OpenMP threads only add overhead (10x on a busy 2-core box)
    threads = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    try:
        index.train(sample)
    finally:
        faiss.omp_set_num_threads(threads)
    return index


def make_index(kind: str, vecs: np.ndarray, trained_pq: Any = None) -> Any:
    """A filled index of ``kind`` over ``vecs`` (float32, (n, dim))."""
    import faiss

    dim = vecs.shape[1]
    if kind == "flat":
        index = faiss.IndexFlatL2(dim)
    elif kind == "fp16":
        index = faiss.IndexScalarQuantizer(dim, faiss.ScalarQuantizer.QT_fp16, faiss.METRIC_L2)
    elif kind == "pq":
        index = faiss.clone_index(trained_pq) if trained_pq is not None else train_pq(vecs)
    else:
        raise MapError(f"unknown submap index kind {kind!r}")
    if len(vecs):
        index.add(np.ascontiguousarray(vecs, dtype=np.float32))
    return index


def index_class(kind: str) -> type:
    import faiss

    return {"flat": faiss.IndexFlatL2, "fp16": faiss.IndexScalarQuantizer,
            "pq": faiss.IndexPQFastScan}[kind]


def search(index: Any, kind: str, rerank: np.ndarray | None, q: np.ndarray, k: int,
           factor: int = DEFAULT_RERANK_FACTOR) -> tuple[np.ndarray, np.ndarray]:
    """Top-``k`` (squared L2, row) of one (1, dim) float32 query in one submap, best first."""
    n = index.ntotal
    k = min(k, n)
    if k <= 0:
        return np.zeros(0, np.float32), np.zeros(0, np.int64)
    if kind != "pq":
        dist, _, rows = search_exact_many([(index, k)], q)
        return dist, rows
    rows = np.sort(pq_candidates(index, q, k * max(1, int(factor)))[1])
    dist = exact_sq_l2(rerank, rows, q)
    order = np.argsort(dist, kind="stable")[:k]
    return dist[order], rows[order]


def search_exact_many(found: Sequence[tuple[Any, int]], q: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The exact search of one (1, dim) float32 query in one or several flat/fp16 indexes,
    each with its own ``k`` (1 <= k <= its size), as (squared L2 float32, position of the index
    in ``found``, row) of every hit, each index's hits best first, indexes in ``found``'s order.
    FAISS's search, called back to back with everything else done before or after (issue 31:
    each call scans MBs of vectors and leaves the caches cold, so the Python between two scans —
    FAISS's argument checks, output arrays, the hits' mask, the file guard — cost tens of us per
    submap in a posterior query on a 230-submap map, a few us warm; back to back, that query
    went from 1.20 to 1.17x one global search in the same interleaved run, with the same hits;
    one array of hits, not one per index: fewer numpy calls after the scans)."""
    import faiss

    q = np.ascontiguousarray(q, dtype=np.float32).reshape(1, -1)
    for index, k in found:
        if index.d != q.shape[1] or not 0 < k <= index.ntotal:
            raise MapError(f"search of {k} of {index.ntotal} {index.d}-D vectors with a "
                           f"{q.shape[1]}-D query")
    width = max((k for _, k in found), default=0)
    dist = np.empty((len(found), width), np.float32)
    rows = np.full((len(found), width), -1, np.int64)  # beyond an index's k: no hit
    qp = faiss.swig_ptr(q)
    calls = [(index.search_c, k, faiss.swig_ptr(dist[i]), faiss.swig_ptr(rows[i]))
             for i, (index, k) in enumerate(found)]
    for call, k, dp, rp in calls:
        call(1, qp, k, dp, rp, None)
    keep = (rows >= 0).ravel()  # FAISS leaves -1 where no distance entered its heap (NaN)
    which = np.repeat(np.arange(len(found), dtype=np.int64), width)
    return dist.ravel()[keep], which[keep], rows.ravel()[keep]


def range_search_rows(rows: np.ndarray, q: np.ndarray, radius: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(squared L2, row) of the float32 ``rows`` (n, dim) whose distance to the (1, dim) query
    is below ``radius``: the kernel of ``IndexFlatL2.range_search`` (``range_search_L2sqr``,
    the same distances) run on the caller's array, where an index would scan its own copy (an
    index's heap copy cannot be put in huge-page memory: :func:`.mapped.huge_page_array`)."""
    import faiss

    q = np.ascontiguousarray(q, dtype=np.float32).reshape(1, -1)
    if rows.dtype != np.float32 or rows.ndim != 2 or rows.shape[1] != q.shape[1] \
            or not rows.flags.c_contiguous:
        raise MapError(f"range search of {rows.dtype}{rows.shape} rows with a "
                       f"{q.shape[1]}-D query")
    res = faiss.RangeSearchResult(1)
    faiss.range_search_L2sqr(faiss.swig_ptr(q), faiss.swig_ptr(rows), q.shape[1], 1,
                             len(rows), float(radius), res)
    found = int(faiss.rev_swig_ptr(res.lims, 2)[1])
    return (faiss.rev_swig_ptr(res.distances, found).copy(),
            faiss.rev_swig_ptr(res.labels, found).copy())


def pq_candidates(index: Any, q: np.ndarray, kk: int) -> tuple[np.ndarray, np.ndarray]:
    """Stage 1 of a pq search: the ``kk`` best rows by PQ-approximate distance (approximate
    distances of submaps that share the map's codebook are comparable across submaps)."""
    kk = min(int(kk), index.ntotal)
    if kk <= 0:
        return np.zeros(0, np.float32), np.zeros(0, np.int64)
    dist, idx = index.search(q, kk)
    keep = idx[0] >= 0
    return dist[0][keep], idx[0][keep]


#: the most bytes of float32 rows the re-rank handles at once (this thread's buffers are this
#: size at most: 192 rows at 512-D, so a block's rows, repeated query and differences stay in
#: the core's caches; a query's re-rank, k·rerank_factor = 800 rows, is five blocks). Measured
#: in the localize() of a paper query, alternated in one process on an AVX-512 EPYC (issue 31):
#: 4.1M map, largest pq submap 2.55 -> 2.26 ms, another 2.71 -> 2.23 ms; 1M map 2.20 -> 2.00
#: and 2.12 -> 1.86 ms, against 4 MiB blocks (one block of 800 rows, 4.7 MB written and read
#: again per query); 512 and 256 KiB within 0.08 ms of this, 768 KiB and 128 KiB slower
RERANK_BLOCK_BYTES = 384 * 2 ** 10
#: up to this many bytes of float32 rows, fresh arrays (small heap blocks, no set-up)
RERANK_SMALL_BYTES = 64 * 2 ** 10


def exact_sq_l2(rerank: np.ndarray, rows: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Stage 2: exact squared L2 of ``q`` to the fp16 re-rank vectors of ``rows`` (ascending
    rows read the memory-mapped file in order; each row must be in the file: a row beyond it
    is an IndexError): ``float32(v) - q`` then the sum of squares, the fp16 -> float32
    conversion and the difference in one OpenCV call (F16C SIMD, one thread; exact: every
    fp16 value is a float32). FAISS's fp16 decoder converts one value at a time (issue 31:
    ``benchmarks/bench_scale.py`` compares both) and numpy's cast is slower still; without
    OpenCV the decoder is used, on the calling thread's OpenMP setting
    (:func:`vlm_vpr_ros.maps.search.one_faiss_thread`).

    Above :data:`RERANK_SMALL_BYTES` the rows, the repeated query and the differences go into
    buffers of the calling thread (:func:`vlm_vpr_ros.threads.scratch`), up to
    :data:`RERANK_BLOCK_BYTES` at a time: fresh arrays of that size are blocks that glibc may
    map and the kernel zero-fill at every query (issue 31, 2-core AVX2 EPYC, 800 × 512-D rows:
    4.6 ms in fresh arrays under the node's malloc settings of that time, 0.5 ms in 128 KiB
    blocks of fresh arrays, 0.35-0.44 ms in the thread's buffers; the same floats:
    tests/test_fusion_search.py). Below it fresh arrays cost less than the buffers' set-up (a
    posterior's re-rank reads a few rows of each of many submaps: 11 rows 19 against 48 us)."""
    rows = np.asarray(rows)
    out = np.empty(len(rows), np.float32)
    if not len(rows):
        return out
    dim = int(rerank.shape[1])
    qf = np.asarray(q, np.float32).reshape(1, -1)
    cv2 = _cv2()
    half = tiled = vecs = None  # a few rows: fresh arrays, one block
    block = len(rows)
    if len(rows) * dim * 4 > RERANK_SMALL_BYTES:  # the thread's buffers
        if int(rows.min()) < 0 or int(rows.max()) >= len(rerank):  # np.take(mode="clip")
            raise IndexError(f"re-rank rows outside 0..{len(rerank) - 1}")
        block = min(len(rows), max(8, RERANK_BLOCK_BYTES // (4 * dim)))
        half = scratch("rerank.rows", (block, dim), rerank.dtype)
        if cv2 is not None:
            tiled = scratch("rerank.query", (block, dim))
            tiled[:] = qf
            vecs = scratch("rerank.diff", (block, dim))
    for s in range(0, len(rows), block):
        r = rows[s:s + block]
        n = len(r)
        # mode="clip" (rows checked above): numpy's default mode copies through another buffer
        h = rerank[r] if half is None else np.take(rerank, r, axis=0, out=half[:n], mode="clip")
        if cv2 is not None:
            # q repeated per row: OpenCV copies a broadcast (stride 0) operand element by element
            v = cv2.subtract(h, np.repeat(qf, n, axis=0) if tiled is None else tiled[:n],
                             dst=None if vecs is None else vecs[:n], dtype=cv2.CV_32F)
        else:
            v = _fp16_codec(dim).decode(np.ascontiguousarray(h).view(np.uint8))
            v -= qf
        np.einsum("ij,ij->i", v, v, out=out[s:s + n])
    return out


@functools.lru_cache(maxsize=1)
def _cv2() -> Any:
    try:
        import cv2
    except ImportError:  # pragma: no cover - OpenCV is a dependency; the decoder still works
        return None
    return cv2


@functools.lru_cache(maxsize=8)
def _fp16_codec(dim: int) -> Any:
    import faiss

    return faiss.ScalarQuantizer(dim, faiss.ScalarQuantizer.QT_fp16)


def vectors(index: Any, kind: str, rerank: np.ndarray | None) -> np.ndarray:
    """All descriptors of a submap as float32 (pq: from its fp16 re-rank vectors)."""
    if kind == "pq":
        return np.asarray(rerank, dtype=np.float32)
    return index.reconstruct_n(0, index.ntotal)


def measure_recall(index: Any, kind: str, rerank: np.ndarray | None, vecs: np.ndarray,
                   factor: int = DEFAULT_RERANK_FACTOR, n_queries: int = 32,
                   seed: int = 0) -> dict[str, float]:
    """Recall@1 and @50 of the submap's search vs exact float32 brute force, for queries that
    are references displaced by half the distance to another reference (near-duplicates
    would make every index look perfect)."""
    n = len(vecs)
    if n < 2:
        return {"recall_at_1": 1.0, "recall_at_50": 1.0, "queries": 0}
    rng = np.random.default_rng(seed)
    a, b = rng.integers(0, n, n_queries), rng.integers(0, n, n_queries)
    noise = rng.normal(size=(n_queries, vecs.shape[1])).astype(np.float32)
    noise *= (0.5 * np.linalg.norm(vecs[a] - vecs[b], axis=1)
              / np.maximum(np.linalg.norm(noise, axis=1), 1e-12))[:, None]
    qs = (vecs[a] + noise).astype(np.float32)
    k = min(50, n)
    norms = np.einsum("ij,ij->i", vecs, vecs)
    scores = norms[:, None] - 2.0 * (vecs @ qs.T)  # (n, queries): one BLAS call for all
    r1 = r50 = 0.0
    for j, q in enumerate(qs):
        col = scores[:, j]
        part = np.argpartition(col, k - 1)[:k] if k < n else np.arange(n)
        exact = part[np.lexsort((part, col[part]))]  # by distance, ties by row (stable)
        _, got = search(index, kind, rerank, q[None, :], k, factor)
        r1 += float(len(got) > 0 and got[0] == exact[0])
        r50 += len(set(got.tolist()) & set(exact.tolist())) / k
    return {"recall_at_1": round(r1 / n_queries, 4), "recall_at_50": round(r50 / n_queries, 4),
            "queries": int(n_queries)}
