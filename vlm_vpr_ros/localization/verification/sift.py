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
  test: ``argmax`` over those columns only (gathered once; typically 5-15 % of them), instead
  of ``argmax(axis=0)`` over the whole matrix (a transposed pass: 1.7 of ~7 ms per candidate
  on the machine of issue 31);
* the similarity matrix (~2 MB) and the reference's RootSIFT are written into buffers kept per
  thread (:func:`vlm_vpr_ros.threads.scratch`): allocated per candidate, glibc maps such blocks
  fresh and the kernel zero-fills them every time — under the node's earlier malloc settings
  (blocks from 256 KiB mmapped) that doubled the stage (issue 31: 122-136 against 56-70 ms, SF
  night, one thread);
* the candidates of one query are shared between threads by the stage
  (:mod:`.share`), each product whole on one thread: an earlier split of one product's rows
  over two threads lost time on a quiet machine (a hand-off per product) and was removed.

:func:`match_reference` is the matcher before issue 31 (exact numpy), kept for the comparisons
of ``benchmarks/bench_verify.py`` and the tests.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.threads import scratch
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


def rootsift(des: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """RootSIFT (float32, unit L2 norm) of SIFT descriptors (any numeric dtype), into ``out``
    (float32, the same shape) when given."""
    if out is None:
        d = np.asarray(des, dtype=np.float32)
        d = d / (d.sum(axis=1, keepdims=True) + 1e-7)
        return np.sqrt(d)
    np.copyto(out, des, casting="unsafe")
    np.divide(out, out.sum(axis=1, keepdims=True) + 1e-7, out=out)
    return np.sqrt(out, out=out)


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

    shares_threads = True  # numpy + BLAS on one thread per product

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        self.cfg = from_mapping(NNConfig, config, "nn matcher")
        super().__init__(asdict(self.cfg))
        self.name = "nn"

    @staticmethod
    def _unit(f: LocalFeatures, temporary: bool = False) -> np.ndarray:
        """Unit descriptors; ``temporary``: in this thread's scratch buffer (SIFT)."""
        if f.descriptors.dtype == np.uint8:  # SIFT
            return rootsift(f.descriptors, scratch("ref", f.descriptors.shape)
                            if temporary else None)
        d = np.asarray(f.descriptors, dtype=np.float32)
        return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)

    def prepare(self, query: LocalFeatures) -> np.ndarray:
        return self._unit(query)

    def match(self, prepared: Any, query: LocalFeatures, ref: LocalFeatures) -> np.ndarray:
        q = prepared
        if len(q) < 2 or len(ref) < 2:
            return np.zeros((0, 2), np.int64)
        return mutual_ratio_matches(q, self._unit(ref, temporary=True), self.cfg.ratio,
                                    self.cfg.distance_max, self.cfg.mutual)


def mutual_ratio_matches(q: np.ndarray, r: np.ndarray, ratio: float, distance_max: float,
                         mutual: bool = True) -> np.ndarray:
    """(query row, reference row) pairs of unit descriptors ``q`` (n, d) and ``r`` (m, d), both
    float32: the query's nearest reference passes Lowe's ratio (distance to the nearest <=
    ``ratio`` · to the second) and ``distance_max``, and, with ``mutual``, the reference's
    nearest query is that query (the first one on ties, as ``argmax``). Same pairs as
    :func:`match_reference` (the same product: the same floats)."""
    sim = np.matmul(q, r.T, out=scratch("sim", (len(q), len(r))))  # (n, m) cosine
    # similarities (BLAS reads r transposed in place), in this thread's buffer
    rows = np.arange(len(sim))
    best = sim.argmax(axis=1)
    s1 = sim[rows, best]
    sim[rows, best] = -np.inf  # second best by masking the best (cheaper than a partition)
    s2 = sim.max(axis=1)
    sim[rows, best] = s1
    d1 = np.sqrt(np.maximum(2.0 - 2.0 * s1, 0.0))
    d2 = np.sqrt(np.maximum(2.0 - 2.0 * s2, 0.0))
    keep = np.flatnonzero((d1 <= ratio * d2) & (d1 <= distance_max))
    if mutual and len(keep):
        # the query must be its column's first best row (argmax's rule on ties): only the
        # columns of the pairs that passed the ratio test are read, not the whole matrix
        col = best[keep]
        cols = np.take(sim, col, axis=1, out=scratch("cols", (len(sim), len(col))), mode="clip")
        keep = keep[cols.argmax(axis=0) == keep]
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
