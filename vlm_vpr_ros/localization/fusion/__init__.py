"""Prior-aware fusion: the VLM error model, the posterior over candidates and its calibration
(docs/fusion.md)."""

from vlm_vpr_ros.localization.fusion.error_model import ErrorModel, load_error_models
from vlm_vpr_ros.localization.fusion.posterior import Posterior, fuse

__all__ = ["ErrorModel", "Posterior", "fuse", "load_error_models"]
