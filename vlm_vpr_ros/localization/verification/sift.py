"""The weight-free default: OpenCV RootSIFT + mutual nearest neighbours with Lowe's ratio test.

RootSIFT (Arandjelović & Zisserman 2012): the SIFT descriptor L1-normalised, then square-rooted,
so that the dot product of two descriptors is their Hellinger kernel. OpenCV's SIFT descriptors
are integers in 0..255, so they are stored exactly as uint8 (128 bytes per keypoint) and turned
into RootSIFT when matched.

Matching is hand-written in numpy rather than ``cv2.BFMatcher``: one BLAS product of the query's
descriptors with a reference's gives both directions (query -> reference best two for the ratio
test, reference -> query best one for the mutual check) from one (n, m) similarity matrix, where
BFMatcher would search twice. The product (SIMD float32 GEMM) is most of the cost; around it
(:func:`mutual_ratio_matches`, issue 31):

* the mutual check needs each reference's best query only for the pairs that passed the ratio
  test: the column maxima come from one contiguous reduction and one comparison pass counts
  the rows reaching each maximum; only a column reached by several rows (a tie) is searched
  for its first row (numpy's argmax rule), instead of ``argmax(axis=0)`` over the whole
  matrix (a transposed copy: 1.7 of ~7 ms per candidate here);
* on a machine with two or more usable cores, the query's rows are split in two halves, one
  computed on a helper thread (a plain thread, no spinning team: on a busy machine it waits
  for a core like any task). The halves' products are the same dot products, but a BLAS may
  round a block of rows differently in the last bit (measured on SF night: docs/verification.md);
  ``MATCH_THREADS = 1`` gives the single-product matcher.

:func:`match_reference` is the matcher before issue 31 (exact numpy), kept for the comparisons
of ``benchmarks/bench_verify.py`` and the tests.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.descriptors.local_sift import gray_frame, sift_detect, strongest_first
from vlm_vpr_ros.localization.verification.components import (Component, LocalFeatureExtractor,
                                                              LocalFeatures, Matcher,
                                                              register_feature, register_matcher)


@dataclass(frozen=True)
class SiftConfig:
    max_side: int = 1024  # longer image side before detection (px)
    contrast_threshold: float = 0.04  # OpenCV's default
    edge_threshold: float = 10.0

    def __post_init__(self) -> None:
        if not 32 <= self.max_side <= 8192:
            raise ConfigError(f"sift max_side must be in 32..8192, got {self.max_side}")
        if not (self.contrast_threshold > 0 and self.edge_threshold > 0):
            raise ConfigError("sift contrast_threshold and edge_threshold must be > 0")


class RootSift(LocalFeatureExtractor):
    """OpenCV SIFT on the grayscale image (longer side <= ``max_side``), stored as uint8."""

    descriptor_dtype = np.dtype(np.uint8)
    descriptor_dim = 128

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        self.cfg = from_mapping(SiftConfig, config, "sift")
        super().__init__(asdict(self.cfg))
        self.name = "sift"

    def extract(self, image: np.ndarray, max_keypoints: int) -> LocalFeatures:
        gray, scale = gray_frame(image, self.cfg.max_side)
        xy, des, resp = sift_detect(gray, max_keypoints, self.cfg.contrast_threshold,
                                    self.cfg.edge_threshold)
        return self.from_pass(xy, des, resp, (gray.shape[1], gray.shape[0]), scale,
                              max_keypoints)

    @staticmethod
    def from_pass(xy: np.ndarray, des: np.ndarray, resp: np.ndarray, size: tuple[int, int],
                  scale: float, max_keypoints: int) -> LocalFeatures:
        """Features from a SIFT pass already made (e.g. by the VLAD descriptor)."""
        xy, des8 = strongest_first(xy, des, resp, max_keypoints)
        return LocalFeatures(xy, des8, (int(size[0]), int(size[1])), float(scale))


def rootsift(des: np.ndarray) -> np.ndarray:
    """RootSIFT (float32, unit L2 norm) of SIFT descriptors (any numeric dtype)."""
    d = np.asarray(des, dtype=np.float32)
    d = d / (d.sum(axis=1, keepdims=True) + 1e-7)
    return np.sqrt(d)


@dataclass(frozen=True)
class NNConfig:
    ratio: float = 0.8  # Lowe's ratio on descriptor distances (1 = off)
    mutual: bool = True  # keep a pair only if each is the other's nearest neighbour
    distance_max: float = 2.0  # largest descriptor distance kept (unit vectors: 0..2)

    def __post_init__(self) -> None:
        if not (0.0 < self.ratio <= 1.0 and 0.0 < self.distance_max <= 2.0):
            raise ConfigError("nn ratio must be in (0, 1] and distance_max in (0, 2]")


class MutualNN(Matcher):
    """Nearest neighbours of unit-norm descriptors (RootSIFT or learned), mutual + ratio."""

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        self.cfg = from_mapping(NNConfig, config, "nn matcher")
        super().__init__(asdict(self.cfg))
        self.name = "nn"
        #: threads of one match (None: MATCH_THREADS); not part of the config (same answers)
        self.threads: int | None = None

    @staticmethod
    def _unit(f: LocalFeatures) -> np.ndarray:
        if f.descriptors.dtype == np.uint8:  # SIFT
            return rootsift(f.descriptors)
        d = np.asarray(f.descriptors, dtype=np.float32)
        return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)

    def prepare(self, query: LocalFeatures) -> np.ndarray:
        return self._unit(query)

    def match(self, prepared: Any, query: LocalFeatures, ref: LocalFeatures) -> np.ndarray:
        q = prepared
        if len(q) < 2 or len(ref) < 2:
            return np.zeros((0, 2), np.int64)
        return mutual_ratio_matches(q, self._unit(ref), self.cfg.ratio, self.cfg.distance_max,
                                    self.cfg.mutual, self.threads)


#: threads of one match (the calling thread + helpers); 1 = one product on the calling thread.
#: One: on a quiet 2-core AMD EPYC the stage took 48.9-51.2 ms with one thread and 55.5-66.4
#: with the rows split over two (benchmarks/bench_verify.py, two runs); the split paid only on
#: a machine loaded 16-20 deep, and a node has its intake and executor threads beside it
MATCH_THREADS = 1
SPLIT_MIN_CELLS = 250_000  # smaller products: a thread hand-off costs more than it saves
_pool: tuple[int, ThreadPoolExecutor] | None = None  # (pid, helper): a forked child has none
_pool_lock = threading.Lock()


def _helper() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None or _pool[0] != os.getpid():  # a fork copies the object, not the thread
            _pool = (os.getpid(), ThreadPoolExecutor(max_workers=1,
                                                     thread_name_prefix="nn-match"))
        return _pool[1]


def _rows_part(q: np.ndarray, rt: np.ndarray, sim: np.ndarray) -> tuple[np.ndarray, ...]:
    """Fill ``sim`` = q @ rt; (best column, best and second best similarity, column maxima)."""
    np.matmul(q, rt, out=sim)
    rows = np.arange(len(sim))
    best = sim.argmax(axis=1)
    s1 = sim[rows, best]
    sim[rows, best] = -np.inf  # second best by masking the best (cheaper than a partition)
    s2 = sim.max(axis=1)
    sim[rows, best] = s1
    return best, s1, s2, sim.max(axis=0)


def mutual_ratio_matches(q: np.ndarray, r: np.ndarray, ratio: float, distance_max: float,
                         mutual: bool = True, threads: int | None = None) -> np.ndarray:
    """(query row, reference row) pairs of unit descriptors ``q`` (n, d) and ``r`` (m, d), both
    float32: the query's nearest reference passes Lowe's ratio (distance to the nearest <=
    ``ratio`` · to the second) and ``distance_max``, and, with ``mutual``, the reference's
    nearest query is that query (the first one on ties, as ``argmax``). Same pairs as
    :func:`match_reference` (up to the last bit of a split product; module docstring)."""
    n = len(q)
    rt = np.ascontiguousarray(r.T)
    sim = np.empty((n, len(r)), np.float32)
    threads = MATCH_THREADS if threads is None else int(threads)
    if threads > 1 and n * len(r) >= SPLIT_MIN_CELLS and n >= 64:
        h = n // 2
        other = _helper().submit(_rows_part, q[h:], rt, sim[h:])
        a = _rows_part(q[:h], rt, sim[:h])
        b = other.result()
        best, s1, s2 = (np.concatenate([x, y]) for x, y in zip(a[:3], b[:3]))
        colmax = np.maximum(a[3], b[3])
    else:
        best, s1, s2, colmax = _rows_part(q, rt, sim)
    d1 = np.sqrt(np.maximum(2.0 - 2.0 * s1, 0.0))
    d2 = np.sqrt(np.maximum(2.0 - 2.0 * s2, 0.0))
    keep = np.flatnonzero((d1 <= ratio * d2) & (d1 <= distance_max))
    if mutual and len(keep):
        col = best[keep]
        keep = keep[s1[keep] == colmax[col]]  # the query reaches its column's maximum ...
        col = best[keep]
        if len(keep):  # ... and is the first row that does (argmax's rule on ties): rows
            # reaching each column's maximum counted in one pass, columns with a tie looked up
            reach = (sim == colmax).view(np.uint8).sum(
                axis=0, dtype=np.uint16 if n < 2 ** 16 else np.uint32)
            tied = reach[col] > 1
            if tied.any():
                c = col[tied]
                first = (np.take(sim, c, axis=1) == colmax[c]).argmax(axis=0)
                ok = np.ones(len(keep), dtype=bool)
                ok[tied] = first == keep[tied]
                keep = keep[ok]
    return np.stack([keep, best[keep]], axis=1).astype(np.int64)


def match_reference(q: np.ndarray, r: np.ndarray, ratio: float, distance_max: float,
                    mutual: bool = True) -> np.ndarray:
    """The matcher before issue 31: one product, ``argmax`` over both axes (exact numpy)."""
    sim = q @ r.T  # (nq, nr) cosine similarities
    rows = np.arange(len(q))
    best = sim.argmax(axis=1)
    s1 = sim[rows, best]
    sim[rows, best] = -np.inf
    s2 = sim.max(axis=1)
    sim[rows, best] = s1
    d1 = np.sqrt(np.maximum(2.0 - 2.0 * s1, 0.0))
    d2 = np.sqrt(np.maximum(2.0 - 2.0 * s2, 0.0))
    keep = (d1 <= ratio * d2) & (d1 <= distance_max)
    if mutual:
        keep &= sim.argmax(axis=0)[best] == rows
    idx = np.flatnonzero(keep)
    return np.stack([idx, best[idx]], axis=1).astype(np.int64)


register_feature(Component("sift", RootSift, {},
                           "OpenCV SIFT (<= 1024 px), stored as uint8, matched as RootSIFT"))
register_matcher(Component("nn", MutualNN, {},
                           "mutual nearest neighbours + Lowe ratio 0.8 (numpy BLAS, exact)"))
