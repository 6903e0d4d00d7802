"""Parameter schema of ``vlm_vpr_node`` and its validation (pure: no ROS imports).

Every parameter is a field of :class:`NodeConfig` with its default and a one-line description
(``ros2 param describe`` and docs/node.md show the same text). Provider settings are nested
under ``prior.`` (``prior.base_url``, ``prior.model``, ``prior.lat`` ...) and descriptor options
under ``descriptor_options.``; both are passed through to the registries, which reject unknown
keys. Unknown top-level names and wrongly typed values raise :class:`ConfigError`.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from typing import Any, Mapping

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.localizer import LocalizerConfig

MODES = ("continuous", "on_trigger")
QOS_CHOICES = ("reliable", "best_effort", "sensor_data")
FALLBACK_STATUS = ("no_fix", "fix")
NESTED = ("prior", "descriptor_options")
#: parameters every rclpy node has
ROS_STANDARD = frozenset({"use_sim_time", "start_type_description_service"})


def _p(default: Any, doc: str) -> Any:
    return field(default=default, metadata={"doc": doc})


@dataclass(frozen=True)
class NodeConfig:
    map_dir: str = _p("", "map folder built by `vlm-vpr build-map` (required)")
    descriptor: str = _p("", "descriptor name; must match the map's ('' = the map's own)")
    prior_provider: str = _p("none", "prior source: none, fixed, recorded, answers, openai; "
                                     "settings under prior.*")
    prior_timeout_s: float = _p(30.0, "longest wait for a prior; then a flagged global fix")
    top_p: int = _p(50, "references retrieved before the re-rank by distance to the prior")
    use_submaps: bool = _p(True, "search only the submap(s) nearest to the prior")
    rerank: bool = _p(True, "re-rank the top-p references by haversine distance to the prior")
    n_submaps: int = _p(1, "number of submaps searched around the prior")
    mode: str = _p("continuous", "continuous: query the latest frame every min_period_s; "
                                 "on_trigger: only on the relocalize service")
    min_period_s: float = _p(1.0, "least time between the starts of two queries")
    frame_id: str = _p("", "header.frame_id of the fix ('' = the image's frame_id)")
    qos: str = _p("reliable", "image subscription QoS: reliable, best_effort, sensor_data")
    qos_depth: int = _p(5, "image subscription queue depth (1-10; the node keeps 1 frame)")
    subscribe_raw: bool = _p(True, "subscribe to 'image' (sensor_msgs/Image)")
    subscribe_compressed: bool = _p(False, "subscribe to 'image/compressed'")
    relocalize_wait_s: float = _p(35.0, "relocalize service: wait this long for the new fix "
                                        "(0 = answer at once that it is scheduled)")
    max_frame_age_s: float = _p(2.0, "relocalize uses the latest frame if received within "
                                     "this many seconds, else the next frame")
    fallback_status: str = _p("no_fix", "NavSatFix status of flagged (fallback) fixes: "
                                        "no_fix or fix")
    fallback_min_sigma_m: float = _p(25000.0, "least 1-sigma radius of a flagged fix (m)")
    altitude_m: float = _p(0.0, "altitude published in the fix (images give none)")
    altitude_sigma_m: float = _p(1000.0, "1-sigma of the published altitude (m)")
    diagnostics_period_s: float = _p(1.0, "period of /diagnostics (also sent after each fix)")
    hardware_id: str = _p("vlm_vpr", "DiagnosticStatus.hardware_id")
    prior: dict = field(default_factory=dict, metadata={"doc": "prior provider settings"})
    descriptor_options: dict = field(default_factory=dict,
                                     metadata={"doc": "descriptor settings (device, weights)"})

    def localizer_config(self) -> LocalizerConfig:
        return LocalizerConfig(top_p=self.top_p, use_submaps=self.use_submaps,
                               rerank=self.rerank, n_submaps=self.n_submaps)


#: scalar parameters: name → (default, description), in declaration order
PARAMETERS: dict[str, tuple[Any, str]] = {
    f.name: (f.default, f.metadata["doc"]) for f in dataclasses.fields(NodeConfig)
    if f.name not in NESTED
}
_TYPES = {f.name: f.type for f in dataclasses.fields(NodeConfig)}


def _coerce(name: str, value: Any) -> Any:
    kind = _TYPES[name]
    ok = {"bool": isinstance(value, bool),
          "int": isinstance(value, int) and not isinstance(value, bool),
          "float": isinstance(value, (int, float)) and not isinstance(value, bool),
          "str": isinstance(value, str)}[kind]
    if not ok:
        raise ConfigError(f"parameter {name!r} must be {'an' if kind == 'int' else 'a'} {kind}, "
                          f"got {value!r} "
                          f"({type(value).__name__})")
    return float(value) if kind == "float" else value


def from_params(values: Mapping[str, Any]) -> NodeConfig:
    """Validate flat ROS parameter values (``prior.x`` nested names allowed) into a config."""
    flat: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {n: {} for n in NESTED}
    for key, value in values.items():
        head, _, rest = key.partition(".")
        if head in NESTED and rest:
            nested[head][rest] = value
        elif key in PARAMETERS:
            flat[key] = _coerce(key, value)
        elif key in ROS_STANDARD or key.startswith("qos_overrides."):
            continue  # declared by rclpy itself
        else:
            raise ConfigError(f"unknown parameter {key!r}; valid: {', '.join(PARAMETERS)}, "
                              f"prior.<setting>, descriptor_options.<setting>")
    cfg = NodeConfig(**flat, **nested)
    validate(cfg)
    return cfg


def _require(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


def _choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    _require(value in choices, f"parameter {name!r} is {value!r}; choices: {', '.join(choices)}")


def validate(cfg: NodeConfig) -> None:
    """Raise ConfigError with a clear message for the first invalid value."""
    _require(bool(cfg.map_dir.strip()), "parameter 'map_dir' is required (a map folder built "
                                        "by `vlm-vpr build-map`)")
    _require(os.path.isdir(os.path.expanduser(cfg.map_dir)),
             f"parameter 'map_dir': {cfg.map_dir!r} is not a folder")
    _choice("mode", cfg.mode, MODES)
    _choice("qos", cfg.qos, QOS_CHOICES)
    _choice("fallback_status", cfg.fallback_status, FALLBACK_STATUS)
    for name in ("prior_timeout_s", "max_frame_age_s", "diagnostics_period_s",
                 "altitude_sigma_m"):
        v = getattr(cfg, name)
        _require(math.isfinite(v) and v > 0, f"parameter {name!r} must be > 0, got {v}")
    for name in ("min_period_s", "relocalize_wait_s", "fallback_min_sigma_m"):
        v = getattr(cfg, name)
        _require(math.isfinite(v) and v >= 0, f"parameter {name!r} must be >= 0, got {v}")
    _require(math.isfinite(cfg.altitude_m), "parameter 'altitude_m' must be finite")
    _require(1 <= cfg.qos_depth <= 10, f"parameter 'qos_depth' must be in 1..10, "
                                       f"got {cfg.qos_depth}")
    _require(cfg.subscribe_raw or cfg.subscribe_compressed,
             "subscribe_raw and subscribe_compressed are both false: nothing to localize")
    cfg.localizer_config()  # raises ConfigError on top_p/n_submaps < 1
    from vlm_vpr_ros.priors import available_prior_providers
    from vlm_vpr_ros.config import choose

    choose(cfg.prior_provider, available_prior_providers(), "prior provider")
