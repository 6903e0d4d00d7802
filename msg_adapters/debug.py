"""Debug outputs: ``sensor_msgs/CompressedImage`` (JPEG) and the candidate list as a
``diagnostic_msgs/DiagnosticArray`` (one status per candidate, best first: a typed message that
``ros2 topic echo`` and Foxglove show without a custom message package). Message classes are
imported inside the functions."""

from __future__ import annotations

from typing import Any, Mapping, Sequence


def _stamp(header: Any, stamp_ns: int) -> None:
    header.stamp.sec = int(stamp_ns) // 1_000_000_000
    header.stamp.nanosec = int(stamp_ns) % 1_000_000_000


def compressed_jpeg(data: bytes, stamp_ns: int, frame_id: str) -> Any:
    """A ``CompressedImage`` (format ``jpeg``) holding ``data``."""
    from sensor_msgs.msg import CompressedImage

    msg = CompressedImage(format="jpeg", data=bytes(data))
    _stamp(msg.header, stamp_ns)
    msg.header.frame_id = frame_id
    return msg


def candidates_array(stamp_ns: int, name: str, hardware_id: str,
                     rows: Sequence[Mapping[str, str]],
                     answer: tuple[str, bool, Mapping[str, str]] | None = None) -> Any:
    """A ``DiagnosticArray`` with one OK status per candidate row (name ``<name> <rank>``,
    message = reference id, values = the row), after the ``answer`` when given: ``(name, is a
    fix, values)``, a status of its own (OK for a fix, else WARN; message = the values'
    ``status`` and ``status_reason``)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    arr = DiagnosticArray()
    _stamp(arr.header, stamp_ns)
    if answer is not None:
        title, fix, values = answer
        why = values.get("status_reason", "")
        st = DiagnosticStatus(level=DiagnosticStatus.OK if fix else DiagnosticStatus.WARN,
                              name=title, hardware_id=hardware_id,
                              message=f"{values.get('status', '')}{': ' + why if why else ''}")
        st.values = [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]
        arr.status.append(st)
    for row in rows:
        st = DiagnosticStatus(level=DiagnosticStatus.OK, name=f"{name} {row.get('rank', '')}",
                              hardware_id=hardware_id, message=str(row.get("ref_id", "")))
        st.values = [KeyValue(key=str(k), value=str(v)) for k, v in row.items()]
        arr.status.append(st)
    return arr
