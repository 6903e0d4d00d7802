"""ROS 2 message types for bags: classes, full ``ros2msg`` definitions, RIHS01 type hashes, QoS.

Definitions and hashes come from the interface files the message packages install
(``<prefix>/share/<pkg>/msg/<Type>.msg`` and the ``<Type>.json`` type description that
``rosidl_generator_type_description`` writes), found the way ament does: ``AMENT_PREFIX_PATH``,
then the running interpreter's prefix (pip-installed ROS wheels). The full definition follows
rosbag2's ``ros2msg`` layout: the root ``.msg`` text, then every dependency (depth first, each
level in sorted order, each type once) after a line of 80 ``=`` and ``MSG: pkg/Type``.
"""

from __future__ import annotations

import functools
import importlib
import json
import logging
import os
import re
import sys
from pathlib import Path
from typing import Any

import yaml

from vlm_vpr_ros.errors import BagError

log = logging.getLogger(__name__)

DELIMITER = "=" * 80 + "\n"
_PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16",
                         "uint16", "int32", "uint32", "int64", "uint64", "string", "wstring"})
# a field (or constant) line starts with its type, optionally with an array suffix
_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_TYPE_NAME = re.compile(r"^([a-zA-Z][a-zA-Z0-9_]*)/(?:([a-zA-Z][a-zA-Z0-9_]*)/)?"
                        r"([a-zA-Z][a-zA-Z0-9_]*)$")
#: rmw's "infinite" duration as rosbag2 writes it in QoS profiles
_INFINITE = {"sec": 9223372036, "nsec": 854775807}


def split_type(type_name: str) -> tuple[str, str, str]:
    """``"sensor_msgs/msg/Image"`` or ``"sensor_msgs/Image"`` → (package, namespace, name)."""
    m = _TYPE_NAME.match(type_name.strip())
    if not m:
        raise BagError(f"not a ROS 2 message type name: {type_name!r}")
    return m.group(1), m.group(2) or "msg", m.group(3)


def message_class(type_name: str) -> Any:
    """The rclpy (rosidl Python) class of ``type_name``; BagError if its package is missing."""
    pkg, ns, name = split_type(type_name)
    try:
        module = importlib.import_module(f"{pkg}.{ns}")
        return getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise BagError(f"message type {type_name} is not available in this Python environment "
                       f"(install or source the '{pkg}' interface package): {exc}") from None


def _prefixes() -> list[Path]:
    out = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    out += [Path(sys.prefix), Path(sys.base_prefix)]
    return out


def interface_file(pkg: str, ns: str, name: str, ext: str) -> Path | None:
    """Path of an installed interface file (``.msg``, ``.json``...) or None."""
    candidates = [p / "share" / pkg / ns / f"{name}{ext}" for p in _prefixes()]
    try:  # next to the Python package (wheel layouts: <prefix>/lib/pythonX/site-packages/pkg)
        mod = importlib.import_module(pkg)
        if getattr(mod, "__file__", None):
            for parent in Path(mod.__file__).resolve().parents[1:6]:
                candidates.append(parent / "share" / pkg / ns / f"{name}{ext}")
    except ImportError:
        pass
    return next((c for c in candidates if c.is_file()), None)


def _dependencies(text: str, pkg: str) -> list[str]:
    deps = set()
    for m in _FIELD_TYPE.finditer(text):
        t = m.group(1)
        if t in _PRIMITIVES:
            continue
        deps.add(t if "/" in t else f"{pkg}/{t}")
    return sorted(deps)


@functools.lru_cache(maxsize=None)
def full_definition(type_name: str) -> str:
    """The complete ``ros2msg`` definition text of a type (as rosbag2 stores it in MCAP)."""
    seen: set[str] = set()

    def expand(name: str, depth: int) -> str:
        if depth > 50:
            raise BagError(f"definition of {type_name} nests too deeply")
        pkg, ns, short = split_type(name)
        path = interface_file(pkg, ns, short, ".msg")
        if path is None:
            raise BagError(f"no .msg definition installed for {name} (looked in the share/ "
                           "folders of AMENT_PREFIX_PATH and this Python prefix)")
        text = path.read_text(encoding="utf-8")
        for dep in _dependencies(text, pkg):
            if dep not in seen:
                seen.add(dep)
                text += "\n" + DELIMITER + f"MSG: {dep}\n" + expand(dep, depth + 1)
        return text

    return expand(type_name, 0)


@functools.lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """The RIHS01 type description hash of a type ("" if it cannot be found)."""
    pkg, ns, short = split_type(type_name)
    full = f"{pkg}/{ns}/{short}"
    path = interface_file(pkg, ns, short, ".json")
    if path is not None:
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
            for entry in doc.get("type_hashes", []):
                if entry.get("type_name") == full:
                    return str(entry["hash_string"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("unreadable type description %s: %s", path, exc)
    try:  # computed from the definitions bundled with rosbags (same algorithm as rosidl)
        from rosbags.typesys import Stores, get_typestore

        return str(get_typestore(Stores.ROS2_JAZZY).hash_rihs01(full))
    except (ImportError, KeyError, ValueError) as exc:
        log.warning("no type hash for %s: %s", full, exc)
        return ""


def qos_profile(depth: int = 10, reliable: bool = True) -> dict:
    """A publisher QoS profile in the form rosbag2 (Jazzy) stores ``offered_qos_profiles``."""
    return {
        "history": "keep_last", "depth": depth,
        "reliability": "reliable" if reliable else "best_effort", "durability": "volatile",
        "deadline": dict(_INFINITE), "lifespan": dict(_INFINITE), "liveliness": "automatic",
        "liveliness_lease_duration": dict(_INFINITE), "avoid_ros_namespace_conventions": False,
    }


def qos_yaml(profiles: list[dict]) -> str:
    """``offered_qos_profiles`` as the YAML string stored in MCAP channel metadata."""
    return yaml.safe_dump(profiles, sort_keys=False, default_flow_style=False).rstrip("\n")


def parse_qos(text_or_list: Any) -> list[dict]:
    """Offered QoS profiles from bag metadata (YAML string, or a list in metadata version 9);
    malformed input gives an empty list (callers then use defaults)."""
    if isinstance(text_or_list, list):
        return [p for p in text_or_list if isinstance(p, dict)]
    if not text_or_list:
        return []
    try:
        data = yaml.safe_load(text_or_list)
    except yaml.YAMLError:
        return []
    return [p for p in data if isinstance(p, dict)] if isinstance(data, list) else []
