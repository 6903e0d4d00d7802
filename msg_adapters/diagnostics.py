"""``diagnostic_msgs/DiagnosticArray`` from a level, a message and key/value pairs."""

from __future__ import annotations

import math
from typing import Any, Mapping

from vlm_vpr_ros.errors import ConfigError

#: level names in the order of ``DiagnosticStatus`` (OK=0, WARN=1, ERROR=2, STALE=3)
LEVELS = ("OK", "WARN", "ERROR", "STALE")


def format_value(value: Any) -> str:
    """Text for a diagnostics value: floats in full precision (the shortest text that reads
    back as the same float: a latitude keeps all its digits), None as empty."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    return str(value)


def diagnostic_array(stamp_ns: int, name: str, hardware_id: str, level: str, message: str,
                     values: Mapping[str, Any]) -> Any:
    """One-status ``DiagnosticArray`` (rclpy message); ``level`` is one of :data:`LEVELS`."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    if level not in LEVELS:
        raise ConfigError(f"unknown diagnostic level {level!r}; choices: {', '.join(LEVELS)}")
    arr = DiagnosticArray()
    arr.header.stamp.sec = int(stamp_ns) // 1_000_000_000
    arr.header.stamp.nanosec = int(stamp_ns) % 1_000_000_000
    status = DiagnosticStatus()
    status.level = getattr(DiagnosticStatus, level)
    status.name = name
    status.hardware_id = hardware_id
    status.message = message
    status.values = [KeyValue(key=str(k), value=format_value(v)) for k, v in values.items()]
    arr.status = [status]
    return arr


def status_values(arr: Any, name: str | None = None) -> dict[str, str]:
    """The key/value pairs of the first status (named ``name`` if given) of an array."""
    for st in arr.status:
        if name is None or st.name == name:
            return {kv.key: kv.value for kv in st.values}
    return {}


def level_name(level: Any) -> str:
    """``DiagnosticStatus.level`` (bytes in rclpy, int elsewhere) → "OK"/"WARN"/..."""
    n = level[0] if isinstance(level, (bytes, bytearray)) else int(level)
    return LEVELS[n] if 0 <= n < len(LEVELS) else str(n)
