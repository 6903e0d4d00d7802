"""OpenCV SIFT on a resized grayscale frame, shared by the VLAD global descriptor and the
verification stage (:mod:`vlm_vpr_ros.localization.verification.sift`), so that a map built with
``vlad_rootsift`` computes SIFT once per image for both (docs/verification.md)."""

from __future__ import annotations

import cv2
import numpy as np

from vlm_vpr_ros.files.images import check_rgb


def gray_frame(image: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    """Grayscale copy of an RGB image whose longer side is at most ``max_side`` (INTER_AREA),
    and the scale back to the original (original pixel = frame pixel * scale)."""
    gray = cv2.cvtColor(check_rgb(image), cv2.COLOR_RGB2GRAY)
    h, w = gray.shape
    s = max_side / max(h, w)
    if s >= 1.0:
        return gray, 1.0
    out = cv2.resize(gray, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    return out, max(h, w) / max(out.shape)


def sift_detect(gray: np.ndarray, max_keypoints: int, contrast_threshold: float = 0.04,
                edge_threshold: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV SIFT in OpenCV's order: keypoints (n, 2) float32, descriptors (n, 128) float32
    (integers 0..255) and responses (n,) float32; empty arrays when nothing is detected."""
    sift = cv2.SIFT_create(nfeatures=int(max_keypoints), contrastThreshold=contrast_threshold,
                           edgeThreshold=edge_threshold)
    kps, des = sift.detectAndCompute(gray, None)
    if des is None or not kps:
        return (np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32),
                np.zeros(0, np.float32))
    return (np.array([k.pt for k in kps], np.float32).reshape(-1, 2), des.astype(np.float32),
            np.array([k.response for k in kps], np.float32))


def strongest_first(xy: np.ndarray, des: np.ndarray, response: np.ndarray,
                    k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` strongest keypoints, strongest first, descriptors as uint8 (lossless: OpenCV's
    SIFT descriptors are integers in 0..255)."""
    order = np.argsort(-response, kind="stable")[:k]
    return xy[order], np.clip(des[order], 0, 255).astype(np.uint8)
