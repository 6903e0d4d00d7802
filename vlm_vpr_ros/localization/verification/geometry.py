"""Geometric verification: the tentative matches consistent with one fundamental matrix.

OpenCV's USAC with MAGSAC++ scoring (``cv2.USAC_MAGSAC``, Barath et al. 2020): robust to the
threshold, which is the largest residual (pixels of the extraction frame) it considers. Images of
one place from different viewpoints are related by a fundamental matrix (a homography would only
hold for planar scenes or pure rotations), so F is the general check, as in hloc and COLMAP.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlm_vpr_ros.errors import ConfigError

#: fewest tentative matches worth a robust fit (F needs 7-8; fewer inliers are noise)
MIN_MATCHES = 12


@dataclass(frozen=True)
class GeometryConfig:
    method: str = "magsac"  # magsac (cv2.USAC_MAGSAC) or ransac (cv2.FM_RANSAC)
    threshold_px: float = 1.5  # largest residual considered (extraction-frame pixels)
    confidence: float = 0.999
    max_iters: int = 2000
    min_matches: int = MIN_MATCHES

    def __post_init__(self) -> None:
        if self.method not in ("magsac", "ransac"):
            raise ConfigError(f"unknown geometry method {self.method!r}; choices: magsac, "
                              "ransac")
        if not (self.threshold_px > 0 and 0 < self.confidence < 1 and self.max_iters >= 10
                and self.min_matches >= 8):
            raise ConfigError("geometry: threshold_px > 0, confidence in (0, 1), "
                              "max_iters >= 10 and min_matches >= 8 required")


def fundamental_inliers(pts_q: np.ndarray, pts_r: np.ndarray,
                        cfg: GeometryConfig = GeometryConfig()) -> np.ndarray:
    """Boolean inlier mask of the correspondences ``pts_q[i] <-> pts_r[i]`` ((m, 2) pixels);
    all False when there are fewer than ``min_matches`` or no model is found."""
    import cv2

    m = len(pts_q)
    if m < cfg.min_matches:
        return np.zeros(m, bool)
    a = np.ascontiguousarray(pts_q, dtype=np.float64).reshape(-1, 1, 2)
    b = np.ascontiguousarray(pts_r, dtype=np.float64).reshape(-1, 1, 2)
    method = cv2.USAC_MAGSAC if cfg.method == "magsac" else cv2.FM_RANSAC
    try:
        F, mask = cv2.findFundamentalMat(a, b, method, cfg.threshold_px, cfg.confidence,
                                         cfg.max_iters)
    except cv2.error:  # degenerate input (all points on a line, duplicates)
        return np.zeros(m, bool)
    if F is None or mask is None or F.shape[0] < 3:
        return np.zeros(m, bool)
    return mask.ravel().astype(bool)[:m]
