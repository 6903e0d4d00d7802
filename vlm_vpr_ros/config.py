"""Strict construction of config dataclasses from plain dicts: unknown keys are errors."""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, TypeVar

from vlm_vpr_ros.errors import ConfigError

T = TypeVar("T")


def from_mapping(cls: type[T], values: Mapping[str, Any] | None, what: str = "") -> T:
    """Build dataclass ``cls`` from ``values``; raise ConfigError listing valid keys on a typo."""
    values = dict(values or {})
    fields = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - fields)
    if unknown:
        label = what or cls.__name__
        raise ConfigError(
            f"unknown {label} option(s) {unknown}; valid options: {sorted(fields)}"
        )
    try:
        return cls(**values)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"invalid {what or cls.__name__} options {values}: {exc}") from exc


def choose(name: str, choices: Mapping[str, Any], what: str) -> Any:
    """Look ``name`` up in a registry; an unknown name raises an error listing the choices."""
    try:
        return choices[name]
    except KeyError:
        raise ConfigError(
            f"unknown {what} {name!r}; choices: {', '.join(sorted(choices)) or '(none)'}"
        ) from None


def parse_kv(items: list[str] | None) -> dict[str, Any]:
    """Parse CLI ``key=value`` pairs; values are read as JSON when possible, else as strings."""
    import json

    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"expected key=value, got {item!r}")
        key, raw = item.split("=", 1)
        try:
            out[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            out[key.strip()] = raw
    return out
