"""The paper's deep VPR models as descriptor presets: ``cosplace``, ``eigenplaces``, ``mixvpr``
(512-D), ``mixvpr_4096`` and ``boq`` (16384-D), all ResNet-50, loading the official checkpoints.

Importing this package registers the presets without importing torch; torch is imported when a
preset is instantiated. Config keys: ``weights``, ``device``, ``batch_size``, ``fp16``,
``resize`` (see :class:`vlm_vpr_ros.descriptors.deep.torch_descriptor.DeepConfig`).
"""

from __future__ import annotations

from typing import Any, Mapping

from vlm_vpr_ros.descriptors import DescriptorPreset, GlobalDescriptor, register_descriptor
from vlm_vpr_ros.descriptors.deep.specs import MODEL_SPECS, ModelSpec, get_spec
from vlm_vpr_ros.errors import DescriptorError

__all__ = ["MODEL_SPECS", "ModelSpec", "get_spec", "create_deep_descriptor"]


def create_deep_descriptor(name: str, config: Mapping[str, Any] | None = None
                           ) -> GlobalDescriptor:
    """Instantiate deep model ``name`` (torch is imported here, not at package import)."""
    spec = get_spec(name)
    try:
        from vlm_vpr_ros.descriptors.deep.torch_descriptor import DeepDescriptor
    except ImportError as exc:
        raise DescriptorError(f"descriptor {name!r} needs PyTorch, which cannot be imported: "
                              f"{exc}") from exc
    return DeepDescriptor(spec, config)


def _factory(name: str):
    return lambda config: create_deep_descriptor(name, config)


for _spec in MODEL_SPECS.values():
    register_descriptor(DescriptorPreset(name=_spec.name, factory=_factory(_spec.name),
                                         defaults={}, summary=_spec.summary, dim=_spec.dim))
