"""Learned local features and matchers (kornia): DISK keypoints + LightGlue.

Registered as ``disk`` (feature) and ``lightglue`` (matcher); the ``disk_lightglue`` preset
combines them. torch and kornia are imported when one is created, never at import time, so the
weight-free default never needs them. Weights are the official checkpoints, loaded from a local
file the way the global descriptors load theirs (:mod:`vlm_vpr_ros.descriptors.deep.weights`:
``torch.load(weights_only=True)``, every key checked, no random fallback); nothing is downloaded:

* DISK: ``weights=PATH``, else ``<torch hub>/checkpoints/depth-save.pth`` (the file of
  ``kornia.feature.DISK.from_pretrained("depth")``); a plain state_dict or one wrapped under
  ``extractor`` (the official container).
* LightGlue for DISK: ``weights=PATH``, else ``<torch hub>/checkpoints/disk_lightglue.pth`` (the
  official release asset of cvg/LightGlue v0.1_arxiv); the official key names
  (``self_attn.<i>`` / ``cross_attn.<i>``) and kornia's (``transformers.<i>.*``) are both read.

DISK descriptors are stored as float16 (128 x 2 bytes per keypoint).
"""

from __future__ import annotations

import logging
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.descriptors.deep.weights import (check_state_dict, file_sha256,
                                                  hub_checkpoint_dir, read_state_dict)
from vlm_vpr_ros.errors import ConfigError, DescriptorError
from vlm_vpr_ros.files.images import check_rgb
from vlm_vpr_ros.localization.verification.components import (Component, LocalFeatureExtractor,
                                                              LocalFeatures, Matcher,
                                                              register_feature, register_matcher)

log = logging.getLogger(__name__)
DISK_RELEASE = "depth-save.pth"
LIGHTGLUE_RELEASE = "disk_lightglue.pth"
#: the architecture of the official DISK LightGlue (cvg/LightGlue v0.1_arxiv)
LIGHTGLUE_DISK = {"input_dim": 128, "descriptor_dim": 256, "n_layers": 9, "num_heads": 4}


def _weights_path(weights: str, release: str, what: str) -> Path:
    path = Path(weights).expanduser() if weights else hub_checkpoint_dir() / release
    if not path.is_file():
        where = "" if weights else " (no weights=PATH given; looked in the torch hub cache)"
        raise DescriptorError(f"{what}: checkpoint {path} does not exist{where}; download the "
                              f"official {release} on a connected machine and pass its path "
                              "as weights=PATH")
    return path


def load_checkpoint(model: Any, path: Path, what: str, rename: bool = False) -> str:
    """Load ``path`` into ``model`` (weights_only, strict, every key checked); returns the
    file's sha256. ``rename``: map the official LightGlue names to kornia's."""
    state = read_state_dict(path, f"{what} checkpoint")
    if rename:
        state = {re.sub(r"^(self_attn|cross_attn)\.(\d+)\.", r"transformers.\2.\1.", k): v
                 for k, v in state.items()}
        own = model.state_dict()
        for k in ("confidence_thresholds",):  # a derived buffer, not in official files
            if k in own and k not in state:
                state[k] = own[k]
    check_state_dict(model, state, f"{what} checkpoint {path}")
    model.load_state_dict(state, strict=True)
    model.eval()
    log.info("loaded %s from %s (%d tensors)", what, path, len(state))
    return file_sha256(path)


@dataclass(frozen=True)
class DiskConfig:
    max_side: int = 1024
    weights: str = ""  # checkpoint path ('' = the torch hub cache)
    device: str = "cpu"
    window_size: int = 5  # non-maximum suppression window (px)

    def __post_init__(self) -> None:
        if not 32 <= self.max_side <= 8192:
            raise ConfigError(f"disk max_side must be in 32..8192, got {self.max_side}")


class DiskFeature(LocalFeatureExtractor):
    """DISK (Tyszkiewicz et al. 2020) keypoints and 128-D descriptors, via kornia."""

    descriptor_dtype = np.dtype(np.float16)
    descriptor_dim = 128

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        import kornia.feature as KF
        import torch

        self.cfg = from_mapping(DiskConfig, config, "disk")
        super().__init__({k: v for k, v in asdict(self.cfg).items()
                          if k not in ("weights", "device")})
        self.name = "disk"
        self._torch = torch
        self.model = KF.DISK().to(self.cfg.device)
        path = _weights_path(self.cfg.weights, DISK_RELEASE, "disk")
        self.weights_sha256 = load_checkpoint(self.model, path, "disk")

    def identity(self) -> dict[str, Any]:
        return {**super().identity(), "weights_sha256": self.weights_sha256}

    def extract(self, image: np.ndarray, max_keypoints: int) -> LocalFeatures:
        import cv2

        torch = self._torch
        rgb = check_rgb(image)
        h, w = rgb.shape[:2]
        s = min(1.0, self.cfg.max_side / max(h, w))
        if s < 1.0:
            rgb = cv2.resize(rgb, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        t = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float() / 255.0
        with torch.inference_mode():
            f = self.model(t.to(self.cfg.device), n=int(max_keypoints),
                           window_size=self.cfg.window_size, pad_if_not_divisible=True)[0]
        score = f.detection_scores.cpu().numpy()
        order = np.argsort(-score, kind="stable")[:max_keypoints]
        xy = f.keypoints.cpu().numpy().astype(np.float32)[order]
        des = f.descriptors.cpu().numpy()[order].astype(np.float16)
        return LocalFeatures(xy, des, (rgb.shape[1], rgb.shape[0]), 1.0 / s)


@dataclass(frozen=True)
class LightGlueConfig:
    features: str = "disk"  # the feature the weights were trained for
    weights: str = ""  # checkpoint path ('' = the torch hub cache)
    device: str = "cpu"
    filter_threshold: float = 0.1  # match confidence threshold
    depth_confidence: float = 0.95  # early stop (-1: off)
    width_confidence: float = 0.99  # point pruning (-1: off)

    def __post_init__(self) -> None:
        if self.features != "disk":
            raise ConfigError(f"lightglue features {self.features!r}: choices: disk")
        if not 0.0 < self.filter_threshold < 1.0:
            raise ConfigError("lightglue filter_threshold must be in (0, 1)")


class LightGlue(Matcher):
    """LightGlue (Lindenberger et al. 2023), via kornia, with the official DISK weights."""

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        import kornia.feature as KF
        import torch

        self.cfg = from_mapping(LightGlueConfig, config, "lightglue")
        super().__init__({k: v for k, v in asdict(self.cfg).items()
                          if k not in ("weights", "device")})
        self.name = "lightglue"
        self._torch = torch
        self.model = KF.LightGlue(None, **LIGHTGLUE_DISK, flash=False,
                                  filter_threshold=self.cfg.filter_threshold,
                                  depth_confidence=self.cfg.depth_confidence,
                                  width_confidence=self.cfg.width_confidence)
        self.model = self.model.to(self.cfg.device)
        path = _weights_path(self.cfg.weights, LIGHTGLUE_RELEASE, "lightglue")
        self.weights_sha256 = load_checkpoint(self.model, path, "lightglue", rename=True)

    def _side(self, f: LocalFeatures) -> dict[str, Any]:
        torch = self._torch
        dev = self.cfg.device
        return {"keypoints": torch.from_numpy(np.asarray(f.keypoints, np.float32))[None].to(dev),
                "descriptors": torch.from_numpy(np.asarray(f.descriptors, np.float32))[None]
                .to(dev),
                "image_size": torch.tensor([[float(f.size[0]), float(f.size[1])]]).to(dev)}

    def prepare(self, query: LocalFeatures) -> dict[str, Any]:
        return self._side(query)

    def match(self, prepared: Any, query: LocalFeatures, ref: LocalFeatures) -> np.ndarray:
        if len(query) < 2 or len(ref) < 2:
            return np.zeros((0, 2), np.int64)
        with self._torch.inference_mode():
            out = self.model({"image0": prepared, "image1": self._side(ref)})
        return out["matches"][0].cpu().numpy().astype(np.int64).reshape(-1, 2)


register_feature(Component("disk", DiskFeature, {},
                           "DISK keypoints + 128-D descriptors (kornia; official weights from "
                           "a local file), stored as float16"))
register_matcher(Component("lightglue", LightGlue, {},
                           "LightGlue for DISK (kornia; official weights from a local file)"))
