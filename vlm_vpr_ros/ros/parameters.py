"""The node's parameters over ROS: declaration from the schema and runtime tuning.

Every parameter of :mod:`vlm_vpr_ros.runtime.params` is declared once with its descriptor
(type, description, range, read-only). The parameters the schema marks writable
(:data:`~vlm_vpr_ros.runtime.params.RUNTIME_WRITABLE`) may change with ``ros2 param set``:
rclpy checks the descriptor (type, range), then the node validates the whole configuration with
the same :func:`~vlm_vpr_ros.runtime.params.from_params` as at start-up and applies it from the
next query on. A set of a structural parameter is refused with a reason that says how to change
it (``map_reload``, a restart), not rclpy's bare "read-only".
"""

from __future__ import annotations

import math
from typing import Any

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.parameter import Parameter

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.runtime.params import (NESTED, NodeConfig, PARAMETER_SPECS, ParamSpec,
                                        ROS_STANDARD, from_params, refusal_reason,
                                        type_conflicts)

_ROS_TYPES = {"bool": ParameterType.PARAMETER_BOOL, "int": ParameterType.PARAMETER_INTEGER,
              "float": ParameterType.PARAMETER_DOUBLE, "str": ParameterType.PARAMETER_STRING}


def parameter_descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The ROS descriptor of one schema parameter (``ros2 param describe`` shows it)."""
    d = ParameterDescriptor(name=spec.name, type=_ROS_TYPES[spec.kind], description=spec.doc,
                            read_only=spec.read_only)
    if spec.choices:
        d.additional_constraints = f"one of: {', '.join(spec.choices)}"
    if spec.range is not None:
        lo, hi = spec.range
        if spec.kind == "int":
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                         to_value=float(hi), step=0.0)]
    return d


def _structural(name: str) -> bool:
    spec = PARAMETER_SPECS.get(name)
    return (spec is not None and spec.read_only) or name.partition(".")[0] in NESTED


def _differs(a: Any, b: Any) -> bool:
    """``a != b``, with NaN equal to NaN (the unset datum)."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return False
    return a != b


def flat_values(cfg: NodeConfig) -> dict[str, Any]:
    """``cfg`` as the flat parameter names and values :func:`from_params` reads."""
    out = {name: getattr(cfg, name) for name in PARAMETER_SPECS}
    for head in NESTED:
        out.update({f"{head}.{k}": v for k, v in getattr(cfg, head).items()})
    return out


class _Parameters:
    """Mixed into the node (before rclpy's Node, so its ``set_parameters*`` come first)."""

    cfg: NodeConfig
    _map_dir_checked_at_start = True  # the lifecycle node checks it at configure

    def _declare_parameters(self, requested: dict[str, Any] | None) -> NodeConfig:
        """Validate what rclpy received (plus what the command line asked for, which rcl may
        have dropped on a type clash), then declare every parameter once with its descriptor.
        Raises ConfigError on any bad name, type or value."""
        overrides: dict[str, Parameter] = self._parameter_overrides  # rclpy: -p, params files
        received = {k: p.value for k, p in overrides.items()}
        values = {**received, **(requested or {})}
        ours = {k: v for k, v in values.items()
                if k not in ROS_STANDARD and not k.startswith("qos_overrides.")}
        cfg = from_params(ours, check_paths=self._map_dir_checked_at_start)
        clashes = type_conflicts(requested or {}, received)
        if clashes:
            raise ConfigError(clashes[0])
        for name, spec in PARAMETER_SPECS.items():
            if name in overrides:  # the validated value (ints given for floats become floats)
                overrides[name] = Parameter(name, value=getattr(cfg, name))
            self.declare_parameter(name, spec.default, parameter_descriptor(spec))
        for key in sorted(k for k in ours if k.partition(".")[0] in NESTED):
            head = key.partition(".")[0]
            self.declare_parameter(key, overrides[key].value if key in overrides else ours[key],
                                   ParameterDescriptor(
                                       description=f"{head} setting (see docs/node.md)",
                                       read_only=True, dynamic_typing=True))
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        return cfg

    # -- runtime changes ------
    def set_parameters(self, parameter_list: list[Parameter]) -> list[SetParametersResult]:
        return [self.set_parameters_atomically([p]) for p in parameter_list]

    def set_parameters_atomically(self, parameter_list: list[Parameter]) -> SetParametersResult:
        for p in parameter_list:
            if _structural(p.name):
                return SetParametersResult(successful=False, reason=refusal_reason(p.name))
        return super().set_parameters_atomically(parameter_list)

    def _proposed(self, params: list[Parameter]) -> NodeConfig | None:
        """The configuration after ``params`` (None when none of them is ours)."""
        ours = {p.name: p.value for p in params if p.name in PARAMETER_SPECS}
        if not ours:
            return None
        return from_params({**flat_values(self.cfg), **ours}, check_paths=False)

    def _check_parameters(self, params: list[Parameter]) -> SetParametersResult:
        try:
            self._proposed(params)
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params: list[Parameter]) -> None:
        new = self._proposed(params)
        if new is None:
            return
        changed = [n for n in PARAMETER_SPECS if _differs(getattr(self.cfg, n), getattr(new, n))]
        if not changed:
            return
        old, self.cfg = self.cfg, new
        changes = ", ".join(f"{n} {getattr(old, n)!r} -> {getattr(new, n)!r}" for n in changed)
        self._settings_changed()
        self.get_logger().info(f"parameters changed at runtime (next query): {changes}")

    def _settings_changed(self) -> None:  # the wiring passes the new settings on
        raise NotImplementedError
