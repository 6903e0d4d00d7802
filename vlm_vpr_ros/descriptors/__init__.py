"""Descriptor registry: named presets → GlobalDescriptor factories.

A preset is a registry name plus default config. Unknown names raise ConfigError listing the
choices. Deep models register themselves from :mod:`vlm_vpr_ros.descriptors.deep` (imported
lazily so that ``torch`` is only imported when a deep model is asked for).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.descriptors.global_descriptor import GlobalDescriptor, l2_normalize

__all__ = [
    "GlobalDescriptor",
    "DescriptorPreset",
    "available_descriptors",
    "create_descriptor",
    "register_descriptor",
    "l2_normalize",
]


@dataclass(frozen=True)
class DescriptorPreset:
    """A named, documented descriptor configuration (hloc-style)."""

    name: str
    factory: Callable[[Mapping[str, Any]], GlobalDescriptor]
    defaults: Mapping[str, Any] = field(default_factory=dict)
    summary: str = ""
    dim: int | None = None  # declared output dim; None when it is set by fitting


_REGISTRY: dict[str, DescriptorPreset] = {}
# Modules whose import registers presets. Lazy so that the core never needs torch.
_PROVIDER_MODULES = (
    "vlm_vpr_ros.descriptors.vlad",
    "vlm_vpr_ros.descriptors.vlad_xfeat",
    "vlm_vpr_ros.descriptors.deep",
)
_loaded = False


def register_descriptor(preset: DescriptorPreset) -> DescriptorPreset:
    """Add a preset to the registry (called at import time by descriptor modules)."""
    _REGISTRY[preset.name] = preset
    return preset


def _load_providers() -> None:
    global _loaded
    if _loaded:
        return
    for mod in _PROVIDER_MODULES:
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            # Only tolerate the provider module itself being absent (e.g. optional extras).
            if exc.name != mod:
                raise
    _loaded = True


def available_descriptors() -> dict[str, DescriptorPreset]:
    """All registered presets by name."""
    _load_providers()
    return dict(sorted(_REGISTRY.items()))


def create_descriptor(name: str, config: Mapping[str, Any] | None = None) -> GlobalDescriptor:
    """Instantiate preset ``name`` with ``config`` overriding its defaults."""
    preset: DescriptorPreset = choose(name, available_descriptors(), "descriptor")
    merged = {**preset.defaults, **dict(config or {})}
    return preset.factory(merged)
