"""Prior-provider registry: ``none``, ``fixed``, ``recorded`` here; ``openai`` and ``answers``
register from :mod:`vlm_vpr_ros.priors.vlm` (the VLM client)."""

from __future__ import annotations

import importlib
import inspect
import json
from typing import Any, Callable, Mapping

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.priors.provider import Prior, PriorProvider, PriorQuery, PriorResult
from vlm_vpr_ros.priors.simple import FixedPrior, NoPrior, RecordedPrior

__all__ = [
    "Prior", "PriorProvider", "PriorQuery", "PriorResult",
    "available_prior_providers", "create_prior_provider", "register_prior_provider",
]

_REGISTRY: dict[str, Callable[..., PriorProvider]] = {
    "none": NoPrior,
    "fixed": FixedPrior,
    "recorded": RecordedPrior,
}
_PROVIDER_MODULES = ("vlm_vpr_ros.priors.vlm",)
_loaded = False


def register_prior_provider(name: str, factory: Callable[..., PriorProvider]) -> None:
    _REGISTRY[name] = factory


def available_prior_providers() -> dict[str, Callable[..., PriorProvider]]:
    global _loaded
    if not _loaded:
        for mod in _PROVIDER_MODULES:
            try:
                importlib.import_module(mod)
            except ModuleNotFoundError as exc:
                if exc.name != mod:
                    raise
        _loaded = True
    return dict(sorted(_REGISTRY.items()))


def _as_mapping(value: Any, key: str) -> dict[str, Any]:
    if isinstance(value, str):  # a JSON string (ROS string parameter)
        try:
            value = json.loads(value)
        except ValueError:
            raise ConfigError(f"prior option {key!r} is not a JSON object") from None
    if not isinstance(value, dict):
        raise ConfigError(f"prior option {key!r} is not a mapping")
    return dict(value)


def _nest(config: dict[str, Any]) -> dict[str, Any]:
    """Fold dotted keys into dict options: ``extra_body.top_k: 20`` (what a ROS parameters
    file gives for a nested mapping) becomes ``extra_body: {"top_k": 20}``, merged with an
    ``extra_body`` given whole."""
    out = {k: v for k, v in config.items() if "." not in str(k)}
    for key in sorted(k for k in config if "." in str(k)):
        *heads, leaf = str(key).split(".")
        node, path = out, ""
        for head in heads:
            path = f"{path}.{head}" if path else head
            node[head] = _as_mapping(node[head], path) if head in node else {}
            node = node[head]
        node[leaf] = config[key]
    return out


def create_prior_provider(name: str, config: Mapping[str, Any] | None = None) -> PriorProvider:
    """Create provider ``name`` from keyword ``config``; unknown names/keys raise ConfigError."""
    factory = choose(name, available_prior_providers(), "prior provider")
    config = _nest(dict(config or {}))
    params = inspect.signature(factory).parameters
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        unknown = sorted(set(config) - set(params))
        if unknown:
            raise ConfigError(f"unknown option(s) {unknown} for prior provider {name!r}; "
                              f"valid: {sorted(params)}")
    try:
        return factory(**config)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"prior provider {name!r}: invalid option value: {exc}") from None
