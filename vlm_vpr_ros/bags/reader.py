"""Reading rosbag2 bags: MCAP folders (``metadata.yaml``), single ``.mcap`` files and sqlite3
``.db3`` bags, with clear errors and partial reads.

A truncated or corrupt file does not raise in the middle of a run: :meth:`BagReader.messages`
yields every message read before the damage and records what went wrong in
:attr:`BagReader.problems` (also logged). Missing topics/types raise :class:`BagError` listing
what the bag has.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

import yaml

from vlm_vpr_ros.bags.messages import message_class
from vlm_vpr_ros.errors import BagError

log = logging.getLogger(__name__)

STORAGE_BY_SUFFIX = {".mcap": "mcap", ".db3": "sqlite3"}


@dataclass(frozen=True)
class TopicInfo:
    name: str
    type: str
    count: int | None  # None when unknown (damaged file)
    serialization_format: str = "cdr"
    qos: tuple = ()


@dataclass(frozen=True)
class RawMessage:
    topic: str
    type: str
    log_time_ns: int
    data: bytes


@dataclass
class BagReader:
    """An opened bag. Construct with :func:`open_bag`."""

    path: Path
    storage: str
    files: list[Path]
    topics: dict[str, TopicInfo] = field(default_factory=dict)
    metadata: dict | None = None
    problems: list[str] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        """False once a truncation/corruption was met while listing or reading."""
        return not self.problems

    def describe(self) -> str:
        """One line per topic: what the bag has (used in error messages)."""
        if not self.topics:
            return "(no topics)"
        return "; ".join(f"{t.name} [{t.type}, {'?' if t.count is None else t.count} msgs]"
                         for t in sorted(self.topics.values(), key=lambda t: t.name))

    def _problem(self, text: str) -> None:
        if text not in self.problems:
            self.problems.append(text)
            log.warning("%s", text)

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
        """Serialized messages of ``topics`` (all by default) in time order per file."""
        want = set(topics) if topics is not None else None
        if want is not None and not want:
            return
        reader = _iter_mcap if self.storage == "mcap" else _iter_db3
        for f in self.files:
            yield from reader(self, f, want)

    def find_topic(self, types: Iterable[str], topic: str | None = None,
                   what: str = "topic") -> TopicInfo:
        """The topic to use for ``what``: ``topic`` if given (checked), else the only topic of
        one of ``types``; BagError listing the bag's topics otherwise."""
        types = tuple(types)
        if topic is not None:
            info = self.topics.get(topic)
            if info is None:
                raise BagError(f"{self.path}: no topic {topic!r} for the {what}; the bag has: "
                               f"{self.describe()}")
            if info.type not in types:
                raise BagError(f"{self.path}: topic {topic} has type {info.type}, the {what} "
                               f"needs {' or '.join(types)}; the bag has: {self.describe()}")
            return info
        found = [t for t in self.topics.values() if t.type in types]
        if not found:
            raise BagError(f"{self.path}: no {' or '.join(types)} topic for the {what}; the "
                           f"bag has: {self.describe()}")
        if len(found) > 1:
            names = ", ".join(sorted(t.name for t in found))
            raise BagError(f"{self.path}: several topics could be the {what} ({names}); "
                           "choose one with the topic option")
        return found[0]


def deserialize(msg: RawMessage) -> Any:
    """The rclpy message object of a raw CDR message; BagError if it cannot be decoded."""
    from rclpy.serialization import deserialize_message

    cls = message_class(msg.type)
    try:
        return deserialize_message(msg.data, cls)
    except RuntimeError as exc:
        raise BagError(f"cannot deserialize a {msg.type} message on {msg.topic} at "
                       f"t={msg.log_time_ns} ns: {exc}") from None


# -- opening ------------------------------------------------------------------------------------
def _read_metadata(folder: Path) -> dict | None:
    path = folder / "metadata.yaml"
    if not path.is_file():
        return None
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
        return dict(doc["rosbag2_bagfile_information"])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError) as exc:
        log.warning("%s is unreadable (%s); looking for bag files directly", path, exc)
        return None


def open_bag(path: str | os.PathLike[str]) -> BagReader:
    """Open a bag folder (rosbag2 MCAP or sqlite3, with or without ``metadata.yaml``) or a single
    ``.mcap``/``.db3`` file and list its topics."""
    path = Path(path)
    meta = None
    if path.is_dir():
        meta = _read_metadata(path)
        files = []
        if meta:
            files = [path / Path(str(p)).name for p in meta.get("relative_file_paths") or []]
            missing = [str(f) for f in files if not f.is_file()]
            if missing:
                raise BagError(f"{path}: metadata.yaml lists missing file(s) {missing}")
        if not files:
            files = sorted(p for p in path.iterdir() if p.suffix in STORAGE_BY_SUFFIX)
        if not files:
            raise BagError(f"{path}: no .mcap or .db3 file in this folder (not a rosbag2 bag)")
    elif path.is_file():
        files = [path]
    else:
        raise BagError(f"bag not found: {path}")
    kinds = {STORAGE_BY_SUFFIX.get(f.suffix) for f in files}
    if None in kinds or len(kinds) != 1:
        raise BagError(f"{path}: unsupported bag file(s) {[f.name for f in files]}; supported: "
                       "rosbag2 MCAP (.mcap) and sqlite3 (.db3)")
    bag = BagReader(path, kinds.pop(), files, metadata=meta)
    for f in files:
        (_list_mcap if bag.storage == "mcap" else _list_db3)(bag, f)
    return bag


def parse_qos(text_or_list: Any) -> list[dict]:
    """Offered QoS profiles from bag metadata (a YAML string, or a list in metadata version 9);
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


def _add_topic(bag: BagReader, name: str, type_: str, count: int | None, fmt: str = "cdr",
               qos: Any = None) -> None:
    old = bag.topics.get(name)
    if old is not None:
        total = None if old.count is None or count is None else old.count + count
        bag.topics[name] = TopicInfo(name, old.type, total, old.serialization_format, old.qos)
    else:
        bag.topics[name] = TopicInfo(name, type_, count, fmt, tuple(parse_qos(qos)))


# -- MCAP ---------------------------------------------------------------------------------------
_MCAP_ERRORS: tuple[type[BaseException], ...] = (ValueError, struct.error, EOFError, OSError,
                                                 KeyError, zlib.error)


def _mcap_errors() -> tuple[type[BaseException], ...]:
    """What reading damaged MCAP data raises: mcap's own errors, struct/zlib/OS errors, and the
    chunk decompressors' (zstandard's ``ZstdError``; lz4 raises ``RuntimeError``)."""
    from mcap import stream_reader
    from mcap.exceptions import McapError

    zstd = getattr(stream_reader, "zstandard", None)
    lz4 = getattr(stream_reader, "lz4", None)
    return ((McapError,) + _MCAP_ERRORS + ((zstd.ZstdError,) if zstd is not None else ())
            + ((RuntimeError,) if lz4 is not None else ()))


def _summary(f: Path) -> Any:
    from mcap.reader import make_reader

    with open(f, "rb") as fh:
        try:
            return make_reader(fh).get_summary()
        except _mcap_errors():
            return None


def _list_mcap(bag: BagReader, f: Path) -> None:
    with open(f, "rb") as fh:
        head = fh.read(8)
    if head[:5] != b"\x89MCAP":
        raise BagError(f"{f}: not an MCAP file (bad magic {head!r}); empty or corrupt")
    summary = _summary(f)
    if summary is not None:
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        for cid, ch in summary.channels.items():
            schema = summary.schemas.get(ch.schema_id)
            _add_topic(bag, ch.topic, schema.name if schema else "", counts.get(cid, 0),
                       ch.message_encoding, ch.metadata.get("offered_qos_profiles"))
        return
    bag._problem(f"{f.name}: no MCAP summary (file truncated or not closed); reading it "
                 "sequentially, messages after the damage are lost")
    counts: dict[str, int] = {}
    channels: dict[str, tuple[str, str, Any]] = {}
    for kind, topic, type_, a, b in _stream(bag, f, None):
        if kind == "channel":
            channels.setdefault(topic, (type_, a, b))
        else:
            counts[topic] = counts.get(topic, 0) + 1
    for topic, (type_, enc, qos) in channels.items():
        _add_topic(bag, topic, type_, counts.get(topic, 0), enc, qos)


def _stream(bag: BagReader, f: Path, want: set[str] | None) -> Iterator[tuple]:
    """Sequential record pass (for files without a usable summary). Yields
    ``("channel", topic, type, encoding, qos)`` and ``("message", topic, type, t_ns, data)``."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    schemas: dict[int, str] = {}
    chans: dict[int, tuple[str, str]] = {}
    with open(f, "rb") as fh:
        try:
            for rec in StreamReader(fh, validate_crcs=True).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    chans[rec.id] = (rec.topic, schemas.get(rec.schema_id, ""))
                    yield ("channel", rec.topic, chans[rec.id][1], rec.message_encoding,
                           rec.metadata.get("offered_qos_profiles"))
                elif isinstance(rec, Message) and rec.channel_id in chans:
                    topic, type_ = chans[rec.channel_id]
                    if want is None or topic in want:
                        yield ("message", topic, type_, rec.log_time, bytes(rec.data))
        except _mcap_errors() as exc:
            bag._problem(f"{f.name}: damaged or truncated MCAP after the last complete record "
                         f"({type(exc).__name__}: {exc}); later messages are lost")


def _iter_mcap(bag: BagReader, f: Path, want: set[str] | None) -> Iterator[RawMessage]:
    from mcap.reader import make_reader

    if _summary(f) is None:
        for kind, topic, type_, t, data in _stream(bag, f, want):
            if kind == "message":
                yield RawMessage(topic, type_, int(t), data)
        return
    with open(f, "rb") as fh:
        try:
            reader = make_reader(fh, validate_crcs=True)
            for schema, ch, m in reader.iter_messages(topics=sorted(want) if want else None):
                yield RawMessage(ch.topic, schema.name if schema else "", int(m.log_time),
                                 bytes(m.data))
        except _mcap_errors() as exc:
            bag._problem(f"{f.name}: corrupt MCAP data ({type(exc).__name__}: {exc}); "
                         "later messages are lost")


# -- sqlite3 ------------------------------------------------------------------------------------
def _connect(f: Path) -> sqlite3.Connection:
    uri = f"file:{f.resolve()}?mode=ro&immutable=1"
    return sqlite3.connect(uri, uri=True)


def _list_db3(bag: BagReader, f: Path) -> None:
    try:
        with _connect(f) as db:
            rows = db.execute("SELECT id, name, type, serialization_format, "
                              "offered_qos_profiles FROM topics").fetchall()
            counts = dict(db.execute("SELECT topic_id, COUNT(*) FROM messages "
                                     "GROUP BY topic_id").fetchall())
    except sqlite3.Error as exc:
        raise BagError(f"{f}: not a readable rosbag2 sqlite3 file ({exc})") from None
    for tid, name, type_, fmt, qos in rows:
        _add_topic(bag, name, type_, int(counts.get(tid, 0)), fmt, qos)


def _iter_db3(bag: BagReader, f: Path, want: set[str] | None) -> Iterator[RawMessage]:
    try:
        db = _connect(f)
    except sqlite3.Error as exc:
        raise BagError(f"{f}: cannot open ({exc})") from None
    try:
        topics = {tid: (name, type_) for tid, name, type_ in
                  db.execute("SELECT id, name, type FROM topics")}
        ids = [tid for tid, (name, _) in topics.items() if want is None or name in want]
        if not ids:
            return
        marks = ",".join("?" * len(ids))
        cur = db.execute(f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN "
                         f"({marks}) ORDER BY timestamp, id", ids)
        for tid, t, data in cur:
            name, type_ = topics[tid]
            yield RawMessage(name, type_, int(t), bytes(data))
    except sqlite3.Error as exc:
        bag._problem(f"{f.name}: corrupt sqlite3 data ({exc}); later messages are lost")
    finally:
        db.close()
