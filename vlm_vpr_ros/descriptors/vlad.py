"""Weight-free default descriptor: VLAD over RootSIFT with PCA-whitening, learned from the map.

Pipeline per image: grayscale → resize so the longer side is ``max_side`` → OpenCV SIFT (at most
``n_features`` keypoints) → RootSIFT (L1-normalise, square root) → VLAD on a ``n_words`` codebook
(residual sums, intra-normalised, L2) → PCA to ``pca_dim`` with shrunk whitening → L2.
The codebook and PCA are fitted on the map's own reference images and stored in the map folder,
so no download is ever needed.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.descriptors import DescriptorPreset, register_descriptor
from vlm_vpr_ros.descriptors.global_descriptor import GlobalDescriptor, l2_normalize
from vlm_vpr_ros.descriptors.local_sift import gray_frame, sift_detect
from vlm_vpr_ros.errors import DescriptorError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VladConfig:
    max_side: int = 640
    n_features: int = 1500
    n_words: int = 64
    pca_dim: int = 256
    whiten: bool = True
    whiten_shrink: float = 0.1  # eigenvalue floor, as a fraction of the mean eigenvalue
    fit_max_images: int = 2000
    fit_max_features: int = 200_000
    seed: int = 0

    def __post_init__(self) -> None:
        """Every value in range before any work: a bad option is one line at the start, not
        an OpenCV assertion (``max_side=1``) or a failure after the whole build
        (``pca_dim=0``)."""
        check_vlad_ints(self, {"max_side": (32, 16384), "n_features": (1, 100_000),
                               "n_words": (2, 4096), "pca_dim": (1, 4096 * 128),
                               "fit_max_images": (2, 10_000_000),
                               "fit_max_features": (4 * 2, 100_000_000),
                               "seed": (0, 2 ** 32 - 1)})
        if not isinstance(self.whiten, bool):
            raise ValueError(f"whiten must be true or false, got {self.whiten!r}")
        w = self.whiten_shrink
        if (not isinstance(w, (int, float)) or isinstance(w, bool) or not math.isfinite(w)
                or not 0 <= w <= 1e6):
            raise ValueError(f"whiten_shrink must be a finite number >= 0, got {w!r}")


def check_vlad_ints(cfg: Any, ranges: Mapping[str, tuple[int, int]]) -> None:
    """ValueError naming the first integer setting of a VLAD config outside its range, or a
    codebook sample too small for its words (``fit_max_features < 4 x n_words``)."""
    for name, (lo, hi) in ranges.items():
        v = getattr(cfg, name)
        if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
            raise ValueError(f"{name} must be an integer in {lo}..{hi}, got {v!r}")
    if cfg.fit_max_features < 4 * cfg.n_words:
        raise ValueError(f"fit_max_features must be at least 4 x n_words "
                         f"({4 * cfg.n_words}), got {cfg.fit_max_features}")


class VladRootSift(GlobalDescriptor):
    """VLAD + RootSIFT global descriptor (see module docstring)."""

    needs_fit = True

    def __init__(self, config: Mapping[str, Any] | None = None, name: str = "vlad_rootsift"):
        self.cfg = from_mapping(VladConfig, config, "vlad_rootsift")
        super().__init__(asdict(self.cfg))
        self.name = name
        self.centroids: np.ndarray | None = None
        self.pca_mean: np.ndarray | None = None
        self.pca_proj: np.ndarray | None = None
        self.pca_scale: np.ndarray | None = None

    # -- interface ---------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        return int(self.pca_proj.shape[1]) if self.pca_proj is not None else self.cfg.pca_dim

    @property
    def preprocessing(self) -> dict[str, Any]:
        return {"color": "gray", "resize_max_side": self.cfg.max_side, "local": "rootsift"}

    @property
    def fitted(self) -> bool:
        return self.centroids is not None and self.pca_proj is not None

    def fit(self, images: Iterable[np.ndarray], progress: bool = True) -> None:
        """Learn the codebook (k-means on RootSIFT) and PCA-whitening from reference images."""
        import faiss

        locals_: list[np.ndarray] = [self.local_features(im) for im in images]
        if len(locals_) < 2:
            raise DescriptorError("vlad_rootsift needs at least 2 images to fit")
        stacked = np.concatenate([f for f in locals_ if len(f)], axis=0)
        if len(stacked) < self.cfg.n_words * 4:
            raise DescriptorError(f"too few local features ({len(stacked)}) to learn "
                                  f"{self.cfg.n_words} visual words")
        rng = np.random.default_rng(self.cfg.seed)
        if len(stacked) > self.cfg.fit_max_features:
            stacked = stacked[rng.choice(len(stacked), self.cfg.fit_max_features, replace=False)]
        km = faiss.Kmeans(stacked.shape[1], self.cfg.n_words, niter=25, seed=self.cfg.seed,
                          verbose=False)
        km.train(np.ascontiguousarray(stacked, dtype=np.float32))
        self.centroids = km.centroids.astype(np.float32)
        raw = np.stack([self._vlad(f) for f in locals_])
        self._fit_pca(raw)
        log.info("vlad_rootsift fitted: %d words, %d images, dim %d",
                 self.cfg.n_words, len(locals_), self.dim)

    def state_arrays(self) -> dict[str, np.ndarray]:
        self._require_fit()
        return {"centroids": self.centroids, "pca_mean": self.pca_mean,
                "pca_proj": self.pca_proj, "pca_scale": self.pca_scale}

    def load_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        missing = {"centroids", "pca_mean", "pca_proj", "pca_scale"} - set(arrays)
        if missing:
            raise DescriptorError(f"vlad_rootsift state lacks {sorted(missing)}")
        c, m, p, s = (np.asarray(arrays[k], dtype=np.float32)
                      for k in ("centroids", "pca_mean", "pca_proj", "pca_scale"))
        big = self.cfg.n_words * 128
        if c.shape != (self.cfg.n_words, 128) or m.shape != (big,) or p.ndim != 2 \
                or p.shape[0] != big or s.shape != (p.shape[1],):
            raise DescriptorError(
                f"vlad_rootsift state shapes do not match the config (n_words="
                f"{self.cfg.n_words}): centroids {c.shape}, mean {m.shape}, proj {p.shape}, "
                f"scale {s.shape}")
        self.centroids, self.pca_mean, self.pca_proj, self.pca_scale = c, m, p, s

    def describe(self, images: Sequence[np.ndarray]) -> np.ndarray:
        self._require_fit()
        if len(images) == 0:
            return np.zeros((0, self.dim), np.float32)
        raw = np.stack([self._vlad(self.local_features(im)) for im in images])
        return self._project(raw)

    # -- internals ---------------------------------------------------------------------------
    def _require_fit(self) -> None:
        if not self.fitted:
            raise DescriptorError("vlad_rootsift is not fitted: build a map first (its codebook "
                                  "and PCA are learned from the map's reference images)")

    def local_features(self, image: np.ndarray) -> np.ndarray:
        """RootSIFT descriptors (N, 128) float32 of one RGB image."""
        return self._rootsift(self.sift(image)[1])

    def sift(self, image: np.ndarray) -> tuple:
        """The SIFT pass of one RGB image: keypoints (frame pixels), raw descriptors,
        responses, the frame's scale back to the image and its (width, height). The
        verification stage reuses it (``describe_with_sift``) when the map's local features
        are this same SIFT."""
        gray, scale = gray_frame(image, self.cfg.max_side)
        xy, des, resp = sift_detect(gray, self.cfg.n_features)
        return xy, des, resp, scale, (gray.shape[1], gray.shape[0])

    def describe_with_sift(self, image: np.ndarray) -> tuple[np.ndarray, tuple]:
        """The global descriptor of one image and its SIFT pass (see :meth:`sift`)."""
        self._require_fit()
        pass_ = self.sift(image)
        return self._project(self._vlad(self._rootsift(pass_[1]))[None, :])[0], pass_

    @staticmethod
    def _rootsift(des: np.ndarray) -> np.ndarray:
        if len(des) == 0:
            return np.zeros((0, 128), np.float32)
        des = des.astype(np.float32)
        des /= des.sum(axis=1, keepdims=True) + 1e-7
        return np.sqrt(des)

    def _vlad(self, feats: np.ndarray) -> np.ndarray:
        assert self.centroids is not None
        k, d = self.centroids.shape
        v = np.zeros((k, d), np.float32)
        if len(feats):
            d2 = ((feats ** 2).sum(1)[:, None] - 2.0 * feats @ self.centroids.T
                  + (self.centroids ** 2).sum(1)[None, :])
            assign = d2.argmin(1)
            np.add.at(v, assign, feats - self.centroids[assign])
        v = l2_normalize(v)  # intra-normalisation (per visual word)
        return l2_normalize(v.reshape(-1))

    def _fit_pca(self, raw: np.ndarray) -> None:
        n = raw.shape[0]
        dim = min(self.cfg.pca_dim, n - 1)
        if dim < self.cfg.pca_dim:
            log.info("vlad_rootsift: only %d fit images, PCA dim clamped %d -> %d",
                        n, self.cfg.pca_dim, dim)
        mean = raw.mean(0)
        _, svals, vt = np.linalg.svd((raw - mean).astype(np.float64), full_matrices=False)
        proj = vt[:dim].T
        eig = (svals[:dim] ** 2) / max(n - 1, 1)
        if self.cfg.whiten:
            scale = 1.0 / np.sqrt(eig + self.cfg.whiten_shrink * eig.mean() + 1e-12)
        else:
            scale = np.ones(dim)
        self.pca_mean = mean.astype(np.float32)
        self.pca_proj = proj.astype(np.float32)
        self.pca_scale = scale.astype(np.float32)

    def _project(self, raw: np.ndarray) -> np.ndarray:
        assert self.pca_proj is not None and self.pca_mean is not None
        y = (raw - self.pca_mean) @ self.pca_proj * self.pca_scale
        return l2_normalize(y)


register_descriptor(DescriptorPreset(
    name="vlad_rootsift",
    factory=lambda cfg: VladRootSift(cfg, "vlad_rootsift"),
    defaults={},
    summary="weight-free default: VLAD (64 words) over RootSIFT, PCA-whitened to 256-D; "
            "codebook and PCA learned from the map's images",
    dim=None,
))
register_descriptor(DescriptorPreset(
    name="vlad_rootsift_fast",
    factory=lambda cfg: VladRootSift(cfg, "vlad_rootsift_fast"),
    defaults={"max_side": 480, "n_features": 800, "n_words": 32, "pca_dim": 128},
    summary="faster/smaller VLAD-RootSIFT: 480 px, 800 keypoints, 32 words, 128-D",
    dim=None,
))
