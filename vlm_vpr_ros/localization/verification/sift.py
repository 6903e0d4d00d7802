"""The weight-free default: OpenCV RootSIFT + mutual nearest neighbours with Lowe's ratio test.

RootSIFT (Arandjelović & Zisserman 2012): the SIFT descriptor L1-normalised, then square-rooted,
so that the dot product of two descriptors is their Hellinger kernel. OpenCV's SIFT descriptors
are integers in 0..255, so they are stored exactly as uint8 (128 bytes per keypoint) and turned
into RootSIFT when matched.

Matching is hand-written in numpy rather than ``cv2.BFMatcher``: one BLAS product of the query's
descriptors with a reference's gives both directions (query -> reference best two for the ratio
test, reference -> query best one for the mutual check) from one (n, m) similarity matrix, where
BFMatcher would search twice.
"""

from __future__ import annotations

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
        sim = q @ self._unit(ref).T  # (nq, nr) cosine similarities
        rows = np.arange(len(q))
        best = sim.argmax(axis=1)
        s1 = sim[rows, best]
        sim[rows, best] = -np.inf  # second best by masking the best (cheaper than a partition)
        s2 = sim.max(axis=1)
        sim[rows, best] = s1
        d1 = np.sqrt(np.maximum(2.0 - 2.0 * s1, 0.0))
        d2 = np.sqrt(np.maximum(2.0 - 2.0 * s2, 0.0))
        keep = (d1 <= self.cfg.ratio * d2) & (d1 <= self.cfg.distance_max)
        if self.cfg.mutual:
            keep &= sim.argmax(axis=0)[best] == rows
        idx = np.flatnonzero(keep)
        return np.stack([idx, best[idx]], axis=1).astype(np.int64)


register_feature(Component("sift", RootSift, {},
                           "OpenCV SIFT (<= 1024 px), stored as uint8, matched as RootSIFT"))
register_matcher(Component("nn", MutualNN, {},
                           "mutual nearest neighbours + Lowe ratio 0.8 (numpy, exact)"))
