"""Writing rosbag2-compatible MCAP bags (``vlm-vpr bag make`` and the evaluation's results bag).

A bag is a folder ``BAG/`` holding ``BAG_0.mcap`` and rosbag2's ``metadata.yaml`` (version 9,
as Jazzy writes it: QoS profiles as a list, ``type_description_hash`` per topic, ``ros_distro``).
The MCAP uses the ``ros2`` profile: ``cdr`` messages serialized by rclpy, ``ros2msg`` schemas with
the full concatenated definition, channel metadata ``offered_qos_profiles`` + ``topic_type_hash``,
and the ``rosbag2`` metadata record. The folder is written under a temporary name and renamed
into place when complete, so a half-written bag never appears under the final name.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from vlm_vpr_ros import __version__
from vlm_vpr_ros.bags.msgdefs import full_definition, qos_profile, qos_yaml, type_hash
from vlm_vpr_ros.errors import BagError
from vlm_vpr_ros.files.csvio import write_csv_atomic

log = logging.getLogger(__name__)

COMPRESSIONS = ("none", "zstd", "lz4")
METADATA_VERSION = 9


@dataclass
class _Topic:
    name: str
    type: str
    channel_id: int
    qos: list[dict]
    hash: str
    count: int = 0
    sequence: int = 0


@dataclass
class _Stats:
    start: int | None = None
    end: int | None = None
    count: int = 0
    topics: dict[str, _Topic] = field(default_factory=dict)


class Rosbag2McapWriter:
    """Write a rosbag2 MCAP bag folder; use as a context manager (aborts cleanly on error)."""

    def __init__(self, path: str | os.PathLike[str], compression: str = "none",
                 overwrite: bool = False, chunk_size: int = 1 << 20) -> None:
        from mcap.writer import CompressionType, Writer

        from vlm_vpr_ros.config import choose

        kind = choose(compression, dict(zip(COMPRESSIONS, ("NONE", "ZSTD", "LZ4"))),
                      "MCAP chunk compression")
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise BagError(f"{self.path} already exists (use --overwrite to replace it)")
        self._tmp = self.path.with_name(f".{self.path.name}.tmp{os.getpid()}")
        if self._tmp.exists():
            shutil.rmtree(self._tmp)
        self._tmp.mkdir(parents=True)
        self.file_name = f"{self.path.name}_0.mcap"
        self._fh = open(self._tmp / self.file_name, "wb")
        self._mcap = Writer(self._fh, chunk_size=chunk_size,
                            compression=getattr(CompressionType, kind))
        self._mcap.start(profile="ros2", library=f"vlm_vpr_ros {__version__} (mcap-python)")
        self._stats = _Stats()
        self._schemas: dict[str, int] = {}
        self._closed = False

    # -- topics and messages -------------------------------------------------------------------
    def add_topic(self, topic: str, type_name: str, qos: list[dict] | None = None) -> None:
        """Declare a topic (rosbag2 full type name, e.g. ``sensor_msgs/msg/Image``)."""
        if topic in self._stats.topics:
            return
        if type_name not in self._schemas:
            self._schemas[type_name] = self._mcap.register_schema(
                name=type_name, encoding="ros2msg",
                data=full_definition(type_name).encode("utf-8"))
        qos = qos or [qos_profile()]
        thash = type_hash(type_name)
        cid = self._mcap.register_channel(
            topic=topic, message_encoding="cdr", schema_id=self._schemas[type_name],
            metadata={"offered_qos_profiles": qos_yaml(qos), "topic_type_hash": thash})
        self._stats.topics[topic] = _Topic(topic, type_name, cid, qos, thash)

    def write(self, topic: str, message: Any, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Write a message (a ROS message object, or already-serialized CDR bytes)."""
        t = self._stats.topics.get(topic)
        if t is None:
            raise BagError(f"topic {topic} was not declared with add_topic()")
        if isinstance(message, (bytes, bytearray, memoryview)):
            data = bytes(message)
        else:
            from rclpy.serialization import serialize_message

            data = serialize_message(message)
        log_time_ns = int(log_time_ns)
        self._mcap.add_message(t.channel_id, log_time=log_time_ns, data=data,
                               publish_time=int(publish_time_ns or log_time_ns),
                               sequence=t.sequence)
        t.sequence += 1
        t.count += 1
        s = self._stats
        s.count += 1
        s.start = log_time_ns if s.start is None else min(s.start, log_time_ns)
        s.end = log_time_ns if s.end is None else max(s.end, log_time_ns)

    # -- metadata ------------------------------------------------------------------------------
    def metadata(self) -> dict:
        """The ``rosbag2_bagfile_information`` mapping (metadata version 9)."""
        s = self._stats
        start = s.start or 0
        duration = (s.end - s.start) if s.count else 0
        return {
            "version": METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": s.count,
            "topics_with_message_count": [
                {"topic_metadata": {"name": t.name, "type": t.type, "serialization_format": "cdr",
                                    "offered_qos_profiles": t.qos,
                                    "type_description_hash": t.hash},
                 "message_count": t.count}
                for t in s.topics.values()],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.file_name],
            "files": [{"path": self.file_name,
                       "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration}, "message_count": s.count}],
            "custom_data": None,
            "ros_distro": "jazzy",
        }

    def close(self) -> Path:
        """Finish the MCAP, write ``metadata.yaml`` and move the folder into place."""
        if self._closed:
            return self.path
        meta = self.metadata()
        self._mcap.add_metadata("rosbag2", {"serialized_metadata": yaml.safe_dump(
            meta, sort_keys=False, default_flow_style=False)})
        self._mcap.finish()
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        text = yaml.safe_dump({"rosbag2_bagfile_information": meta}, sort_keys=False,
                              default_flow_style=False)
        (self._tmp / "metadata.yaml").write_text(text, encoding="utf-8")
        self._closed = True
        if self.path.exists():
            shutil.rmtree(self.path)
        os.replace(self._tmp, self.path)
        log.info("wrote bag %s (%d messages)", self.path, self._stats.count)
        return self.path

    def abort(self) -> None:
        """Drop the partly written bag."""
        if not self._closed:
            self._closed = True
            self._fh.close()
            shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> "Rosbag2McapWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_sidecar(path: Path, rows: list[dict]) -> None:
    """``frames.csv`` beside a made bag: which file each frame came from (for recorded priors)."""
    write_csv_atomic(path, ["index", "stamp_ns", "file", "lat", "lon"], rows)


def now_ns() -> int:
    return time.time_ns()
