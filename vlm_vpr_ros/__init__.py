"""vlm_vpr_ros: VLM-guided visual place recognition for planet-scale geo-localization (ROS 2).

The Python API (docs/api.md)::

    from vlm_vpr_ros import LocalizationPipeline, PriorResult, Prior
    pipe = LocalizationPipeline.open("maps/city")
    prior = Prior(37.77, -122.42, source="operator", sigma_km=5.0)
    hyp = pipe.localize_image(rgb, PriorResult(prior, source="operator"))
    print(hyp.lat, hyp.lon, hyp.uncertainty_m)

The folders follow a query's path — :mod:`.descriptors` → :mod:`.priors` →
:mod:`.localization` (retrieval, fusion, verification) → :mod:`.runtime` (the node's worker) →
:mod:`.ros` (messages) — and a map's: :mod:`.maps` (build, store, edit), :mod:`.distributed`
(Ray), :mod:`.bags` (teach runs, replay). :mod:`.evaluation` scores results; :mod:`.cli` is the
``vlm-vpr`` command; :mod:`.files` holds the atomic writers every output goes through.

The core (everything but :mod:`vlm_vpr_ros.ros`, :mod:`.cli` and :mod:`.bags`) is pure Python: it
never imports rclpy, ROS message packages or mcap. The names below are imported on first use,
so ``import vlm_vpr_ros`` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: public name -> module that defines it
_PUBLIC = {
    "LocalizationPipeline": "vlm_vpr_ros.localization.pipeline",
    "Localizer": "vlm_vpr_ros.localization.localizer",
    "LocalizerConfig": "vlm_vpr_ros.localization.localizer",
    "ReferenceMap": "vlm_vpr_ros.maps.reference_map",
    "build_map": "vlm_vpr_ros.mapping.build_images",
    "build_from_descriptors": "vlm_vpr_ros.mapping.build_descriptors",
    "add_references": "vlm_vpr_ros.mapping.edit",
    "remove_references": "vlm_vpr_ros.mapping.edit",
    "create_descriptor": "vlm_vpr_ros.descriptors",
    "create_prior_provider": "vlm_vpr_ros.priors",
    "Prior": "vlm_vpr_ros.priors.provider",
    "PriorResult": "vlm_vpr_ros.priors.provider",
    "Hypothesis": "vlm_vpr_ros.types",
    "Candidate": "vlm_vpr_ros.types",
    "load_image": "vlm_vpr_ros.files.images",
    "VlmVprError": "vlm_vpr_ros.errors",
}

__all__ = ["__version__", *sorted(_PUBLIC)]


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'vlm_vpr_ros' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
