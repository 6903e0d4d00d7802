"""Writing rosbag2 bags (``vlm-vpr bag make``, the evaluation's results bag), with rosbags.

The format is rosbags' ``rosbag2.Writer``: a folder ``BAG/`` holding ``BAG.mcap`` (or
``BAG.db3``) and ``metadata.yaml`` version 9 (QoS profiles as a list, ``type_description_hash``
per topic, ``custom_data``); ``ros2msg`` schemas and RIHS01 type hashes come from rosbags'
ROS 2 Jazzy type store. What this module adds around it:

* **stage, then rename**: the bag is written in ``.BAG.tmp<pid>/BAG`` beside the target, its
  files and folder are ``fsync``-ed, and only then is it renamed to ``BAG`` (an old bag there is
  replaced last), so a half-written bag never appears under the target name;
* messages as rclpy objects (serialized with ``rclpy.serialization``) or as CDR bytes;
* real chunk CRCs in MCAP bags: rosbags' MCAP writer leaves every chunk's
  ``uncompressed_crc`` 0 ("not computed"), so a flipped byte went unseen; each chunk's CRC-32
  is written in place as the chunk is closed, and readers (rosbags', ours) check it;
* ``ros_distro: jazzy`` (:data:`ROS_DISTRO`, the type store's distribution) where rosbags
  writes its own name: ``metadata.yaml``, the copy of it inside the storage file, and a sqlite3
  bag's ``schema`` table;
* one error type: :class:`~vlm_vpr_ros.errors.BagError` (OS errors: ``OutputError``).
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import sqlite3
import struct
import time
import zlib
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import WriterError

from vlm_vpr_ros import __version__
from vlm_vpr_ros.errors import BagError, OutputError
from vlm_vpr_ros.files.atomic import atomic_write_text, describe_os_error, fsync_tree
from vlm_vpr_ros.files.csvio import write_csv_atomic

log = logging.getLogger(__name__)

STORAGES = ("mcap", "sqlite3")
#: chunk compression of MCAP bags (rosbags writes zstd chunks; sqlite3 bags are uncompressed)
COMPRESSIONS = ("none", "zstd")
METADATA_VERSION = 9
#: the ROS distribution recorded in bags (the messages are Jazzy's: :func:`typestore`)
ROS_DISTRO = "jazzy"
_ROSBAGS_DISTRO = "ros_distro: rosbags"
#: where a chunk record's ``uncompressed_crc`` lies, from the record's first byte (MCAP spec)
_CHUNK_CRC_OFFSET = 1 + 8 + 3 * 8
#: rmw's "infinite" duration as rosbag2 stores it in QoS profiles
_INFINITE = (9223372036, 854775807)


@functools.lru_cache(maxsize=1)
def typestore() -> Any:
    """rosbags' type store of ROS 2 Jazzy (message definitions and RIHS01 hashes)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def qos_profile(depth: int = 10, reliable: bool = True) -> Any:
    """A publisher QoS profile as rosbag2 records it in ``offered_qos_profiles``."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)

    forever = QosTime(*_INFINITE)
    return Qos(history=QosHistory.KEEP_LAST, depth=int(depth),
               reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               durability=QosDurability.VOLATILE, deadline=forever, lifespan=forever,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=forever,
               avoid_ros_namespace_conventions=False)


class BagWriter:
    """Write a rosbag2 bag folder; use as a context manager (aborts cleanly on error).

    ``storage``: "mcap" (default) or "sqlite3"; ``compression``: "none" or "zstd" (MCAP
    chunks). The bag appears at ``path`` only when :meth:`close` has finished it."""

    def __init__(self, path: str | os.PathLike[str], storage: str = "mcap",
                 compression: str = "none", overwrite: bool = False) -> None:
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        from vlm_vpr_ros.config import choose

        plugin = choose(storage, dict(zip(STORAGES, (StoragePlugin.MCAP,
                                                     StoragePlugin.SQLITE3))), "bag storage")
        zstd = choose(compression, dict(zip(COMPRESSIONS, (False, True))), "bag compression")
        if zstd and storage != "mcap":
            raise BagError(f"compression {compression!r} needs --storage mcap (sqlite3 bags "
                           "are written uncompressed)")
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise BagError(f"{self.path} already exists (use --overwrite to replace it)")
        self._stage = self.path.with_name(f".{self.path.name}.tmp{os.getpid()}")
        self._closed = False
        self._topics: dict[str, Any] = {}
        self.count = 0
        try:
            if self._stage.exists():
                shutil.rmtree(self._stage)
            self._stage.mkdir(parents=True)
            self._bag = Writer(self._stage / self.path.name, version=METADATA_VERSION,
                               storage_plugin=plugin)
            if zstd:
                self._bag.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            self._bag.set_custom_data("writer", f"vlm_vpr_ros {__version__}")
            self._bag.open()
            self._distro_in_storage()
            self._crc_in_chunks()
        except OSError as exc:
            shutil.rmtree(self._stage, ignore_errors=True)
            raise OutputError(describe_os_error(exc, self.path)) from None

    def _distro_in_storage(self) -> None:
        """The metadata rosbags hands its storage on close (MCAP metadata record, sqlite3
        ``metadata`` table) names :data:`ROS_DISTRO` instead of "rosbags"."""
        storage = getattr(self._bag, "storage", None)
        close = getattr(storage, "close", None)
        if close is None:
            return

        def close_with_distro(version: int, metadata: str) -> None:
            close(version, metadata.replace(_ROSBAGS_DISTRO, f"ros_distro: {ROS_DISTRO}"))

        storage.close = close_with_distro

    def _crc_in_chunks(self) -> None:
        """Each MCAP chunk's ``uncompressed_crc`` (CRC-32 of its records before compression)
        written where rosbags' writer puts 0: opcode (1) + length (8) + start, end and
        uncompressed size (3 x 8) precede it in the chunk record (MCAP spec, "Chunk")."""
        storage = getattr(self._bag, "storage", None)
        close_chunk = getattr(storage, "close_chunk", None)
        if close_chunk is None:  # sqlite3: no chunks
            return

        def close_chunk_with_crc() -> None:
            crc = zlib.crc32(storage.chunk.bio.getbuffer())
            start = storage.bio.tell()
            close_chunk()
            end = storage.bio.tell()
            storage.bio.seek(start + _CHUNK_CRC_OFFSET)
            storage.bio.write(struct.pack("<I", crc))
            storage.bio.seek(end)

        storage.close_chunk = close_chunk_with_crc

    def _distro_in_metadata(self, staged: Path) -> None:
        """``ros_distro: jazzy`` in the finished bag's ``metadata.yaml`` (and a sqlite3 bag's
        ``schema`` table), where rosbags wrote its own name."""
        meta = staged / "metadata.yaml"
        text = meta.read_text(encoding="utf-8")
        if _ROSBAGS_DISTRO in text:
            atomic_write_text(meta, text.replace(_ROSBAGS_DISTRO, f"ros_distro: {ROS_DISTRO}"))
        for db in staged.glob("*.db3"):
            con = sqlite3.connect(db)
            try:
                with con:
                    con.execute("UPDATE schema SET ros_distro = ? WHERE ros_distro = 'rosbags'",
                                (ROS_DISTRO,))
            finally:
                con.close()

    # -- topics and messages -------------------------------------------------------------------
    def add_topic(self, topic: str, type_name: str, qos: list[Any] | None = None) -> None:
        """Declare a topic (full type name, e.g. ``sensor_msgs/msg/Image``); QoS profiles from
        :func:`qos_profile` (default: reliable, depth 10)."""
        if topic in self._topics:
            return
        store = typestore()
        if type_name not in store.types:
            raise BagError(f"cannot write {topic}: type {type_name} is not in rosbags' ROS 2 "
                           "Jazzy type store")
        try:
            self._topics[topic] = self._bag.add_connection(
                topic, type_name, typestore=store, offered_qos_profiles=qos or [qos_profile()])
        except WriterError as exc:
            raise BagError(f"cannot write {topic} to {self.path}: {exc}") from None

    def write(self, topic: str, message: Any, log_time_ns: int) -> None:
        """Write a message (a ROS message object, or already-serialized CDR bytes)."""
        conn = self._topics.get(topic)
        if conn is None:
            raise BagError(f"topic {topic} was not declared with add_topic()")
        if isinstance(message, (bytes, bytearray, memoryview)):
            data = bytes(message)
        else:
            from rclpy.serialization import serialize_message

            data = serialize_message(message)
        self._bag.write(conn, int(log_time_ns), data)
        self.count += 1

    # -- finishing -----------------------------------------------------------------------------
    def close(self) -> Path:
        """Finish the bag (index, ``metadata.yaml``), make it durable, move it into place."""
        if self._closed:
            return self.path
        self._closed = True
        staged = self._stage / self.path.name
        old = self._stage / ".old"
        try:
            self._bag.close()
            self._distro_in_metadata(staged)
            fsync_tree(staged)
            if self.path.exists():
                os.replace(self.path, old)
            os.replace(staged, self.path)
            fsync_tree(self.path.parent, files=False)
        except OSError as exc:
            raise OutputError(describe_os_error(exc, self.path)) from None
        except (WriterError, sqlite3.Error) as exc:
            raise BagError(f"cannot finish {self.path}: {exc}") from None
        finally:
            shutil.rmtree(self._stage, ignore_errors=True)
        log.info("wrote bag %s (%d messages)", self.path, self.count)
        return self.path

    def abort(self) -> None:
        """Drop the partly written bag (the target is left as it was)."""
        if not self._closed:
            self._closed = True
            self._bag.abort()
            shutil.rmtree(self._stage, ignore_errors=True)

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def bag_files(bag: str | os.PathLike[str]) -> list[Path]:
    """The storage files of a bag folder, as its ``metadata.yaml`` lists them."""
    import yaml

    meta = yaml.safe_load((Path(bag) / "metadata.yaml").read_text(encoding="utf-8"))
    return [Path(bag) / p for p in meta["rosbag2_bagfile_information"]["relative_file_paths"]]


def write_sidecar(path: Path, rows: list[dict]) -> None:
    """``frames.csv`` beside a made bag: which file each frame came from (for recorded priors)."""
    write_csv_atomic(path, ["index", "stamp_ns", "file", "lat", "lon"], rows)


def now_ns() -> int:
    return time.time_ns()
