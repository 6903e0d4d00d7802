"""Verification presets (hloc style): a local feature, a matcher, the geometry check and the
keypoint caps, under one name. ``sift`` is the weight-free default; ``disk_lightglue`` needs the
official DISK and LightGlue checkpoints in local files (:mod:`.learned`).

For maps whose global descriptor is ``vlad_rootsift*``, the ``sift`` preset takes the
descriptor's own SIFT settings (frame size, keypoints), so one SIFT pass per image serves both
the global descriptor and verification, at build time and for every query
(:func:`preset_for_map`); a study on SF night found the same fixes at 640 px as at 1024 px
(docs/verification.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Mapping

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.errors import ConfigError


@dataclass(frozen=True)
class VerifierPreset:
    name: str
    feature: str
    matcher: str
    feature_config: Mapping[str, Any] = field(default_factory=dict)
    matcher_config: Mapping[str, Any] = field(default_factory=dict)
    geometry: Mapping[str, Any] = field(default_factory=dict)
    max_keypoints: int = 1000  # stored per reference
    query_max_keypoints: int = 2000  # extracted per query
    summary: str = ""

    def __post_init__(self) -> None:
        if not (8 <= self.max_keypoints <= 100_000 and 8 <= self.query_max_keypoints
                <= 100_000):
            raise ConfigError("verification keypoint caps must be in 8..100000")


PRESETS: dict[str, VerifierPreset] = {p.name: p for p in (
    VerifierPreset("sift", "sift", "nn", {"max_side": 1024}, {"ratio": 0.8, "mutual": True},
                   {"method": "magsac", "threshold_px": 1.5}, 1000, 2000,
                   "OpenCV RootSIFT (<= 1024 px; vlad_rootsift maps: the descriptor's own "
                   "SIFT), mutual NN + ratio 0.8, MAGSAC fundamental matrix; weight-free"),
    VerifierPreset("disk_lightglue", "disk", "lightglue", {"max_side": 1024}, {},
                   {"method": "magsac", "threshold_px": 1.5}, 1000, 2000,
                   "DISK + LightGlue (kornia), MAGSAC fundamental matrix; official weights "
                   "from local files (feature_options weights=..., matcher_options "
                   "weights=...)"),
)}


def get_preset(name: str) -> VerifierPreset:
    return choose(name, PRESETS, "verification preset")


def preset_for_map(name: str, descriptor_identity: Mapping[str, Any] | None) -> VerifierPreset:
    """The preset as a map built with ``descriptor_identity`` uses it (``sift`` on a
    vlad_rootsift map: the descriptor's frame size and keypoint count)."""
    p = get_preset(name)
    ident = dict(descriptor_identity or {})
    if p.feature == "sift" and str(ident.get("name", "")).startswith("vlad_rootsift"):
        cfg = ident.get("config") or {}
        side, n = int(cfg.get("max_side", 640)), int(cfg.get("n_features", 1500))
        p = replace(p, feature_config={**p.feature_config, "max_side": side},
                    max_keypoints=min(p.max_keypoints, n), query_max_keypoints=n)
    return p
