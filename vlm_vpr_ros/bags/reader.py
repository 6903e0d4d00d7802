"""Reading rosbag2 bags: MCAP folders (``metadata.yaml``), single ``.mcap`` files and sqlite3
``.db3`` bags, with clear errors and partial reads.

**Who reads what.** Every storage file is read by rosbags (``rosbags.rosbag2.Reader`` opened
on the file itself). Only what rosbags cannot do is hand-written, in
:mod:`vlm_vpr_ros.bags.recover`:

* reading a damaged file **up to the damage**: rosbags refuses to open a truncated MCAP (no
  footer/summary) and gives nothing, the recovery reader yields every message recorded before
  the cut and records the problem;
* reading on where rosbags stops inside a file (a chunk failing its CRC): rosbags loads a
  chunk before it yields the equal stamps of the chunk before, so it would lose intact
  messages; the recovery reader skips the messages already yielded and reads to the damage;
* files rosbags refuses although they are readable (an MCAP with another profile, a file it
  raises on for any reason): the recovery reader reads them whole and reports nothing;
* sqlite3 files without an index on ``messages.timestamp``: rosbags asks for ``ORDER BY
  timestamp`` only, which orders equal stamps by row id through that index (rosbag2 and rosbags
  both create it) but in no stated order without it.

``metadata.yaml`` only names the storage files: rosbags' folder reader trusts it and real bags'
metadata lies (``storage_identifier: ''`` makes it raise; QoS text that differs from the
file's makes it match no connection and silently yield nothing), so each file is opened alone.

**Order.** File by file in the bag's file order; within a file by log time, equal log times in
file order (MCAP: position in the file, sqlite3: row id, i.e. the order of recording). This
holds on both paths: rosbags merges MCAP chunks by (log time, chunk offset) and sorts stably
within a chunk, the ``mcap`` library used by the recovery reader does the same, and sqlite3
is read in (timestamp, id) order. A truncated MCAP has no index; it is read in file order.

**Damage.** A truncated or corrupt file does not raise in the middle of a run:
:meth:`BagReader.messages` yields every message read before the damage and records what went
wrong in :attr:`BagReader.problems` (also logged). Missing topics/types raise
:class:`BagError` listing what the bag has.
"""

from __future__ import annotations

import logging
import os
import sqlite3
from contextlib import closing
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path
from typing import Any, Iterable, Iterator

import yaml

from vlm_vpr_ros.bags import recover
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
    #: storage files read by the hand-written recovery reader instead of rosbags
    recovered: list[Path] = field(default_factory=list)

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
        """Serialized messages of ``topics`` (all by default): file by file, each by log time
        with equal times in file order (see the module docstring)."""
        want = set(topics) if topics is not None else None
        if want is not None and not want:
            return
        for f in self.files:
            rows = (recover.messages(f, self.storage, want, self._problem)
                    if f in self.recovered
                    else _rosbags_messages(f, self.storage, want, self._problem))
            for topic, type_, t, data in rows:
                yield RawMessage(topic, type_, t, data)

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


def open_bag(path: str | os.PathLike[str], *, recovery: bool = False) -> BagReader:
    """Open a bag folder (rosbag2 MCAP or sqlite3, with or without ``metadata.yaml``) or a single
    ``.mcap``/``.db3`` file and list its topics. ``recovery=True`` reads every file with the
    hand-written recovery reader instead of rosbags (tests and benchmarks compare the two)."""
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
        rows = None if recovery else _rosbags_topics(f, bag.storage)
        if rows is None:
            bag.recovered.append(f)
            rows = recover.list_topics(f, bag.storage, bag._problem)
        for row in rows:
            _add_topic(bag, *row)
    return bag


def parse_qos(profiles: Any) -> list[dict]:
    """Offered QoS profiles as plain dicts (enum values by lower-case name, durations as
    ``{"sec", "nsec"}``), from rosbags' parsed profiles or the raw metadata (a YAML string, or
    a list in metadata version 9); malformed input gives an empty list (callers then use
    defaults)."""
    from rosbags.rosbag2.metadata import parse_qos as rosbags_parse_qos

    if isinstance(profiles, list) and all(hasattr(p, "_asdict") for p in profiles):
        parsed = profiles
    else:
        try:
            parsed = rosbags_parse_qos(profiles) if profiles else []
        except Exception:  # noqa: BLE001 - any malformed text/structure means "no QoS known"
            return []

    def plain(value: Any) -> Any:
        if hasattr(value, "_asdict"):
            return {k: plain(v) for k, v in value._asdict().items()}
        return value.name.lower() if hasattr(value, "name") else value

    return [plain(p) for p in parsed]


def _add_topic(bag: BagReader, name: str, type_: str, count: int | None, fmt: str = "cdr",
               qos: Any = None) -> None:
    old = bag.topics.get(name)
    if old is not None:
        total = None if old.count is None or count is None else old.count + count
        bag.topics[name] = TopicInfo(name, old.type, total, old.serialization_format, old.qos)
    else:
        bag.topics[name] = TopicInfo(name, type_, count, fmt, tuple(parse_qos(qos)))


# -- rosbags ------------------------------------------------------------------------------------
def _msgtype(name: str) -> str:
    return "" if name == "__schemaless__" else name  # rosbags' name for "no schema"


def _time_indexed(f: Path) -> bool:
    """Whether a sqlite3 file has an index led by ``messages.timestamp`` (then rosbags' ``ORDER
    BY timestamp`` walks it and equal stamps come in row id order)."""
    try:
        with closing(recover.connect(f)) as db:
            return db.execute("SELECT 1 FROM pragma_index_list('messages') AS l, "
                              "pragma_index_info(l.name) AS i WHERE i.seqno = 0 AND "
                              "i.name = 'timestamp'").fetchone() is not None
    except sqlite3.Error:
        return False


def _rosbags_topics(f: Path, storage: str) -> list[recover.TopicRow] | None:
    """The topics of one storage file as rosbags lists them; None where the recovery reader
    has to read the file (rosbags raises, or a sqlite3 file lacks the timestamp index)."""
    from rosbags.rosbag2 import Reader

    if storage == "sqlite3" and not _time_indexed(f):
        log.info("%s has no timestamp index; reading it with the recovery reader (row order "
                 "for equal stamps)", f)
        return None
    try:
        with Reader(f) as reader:
            return [(c.topic, _msgtype(c.msgtype), c.msgcount, c.ext.serialization_format,
                     c.ext.offered_qos_profiles) for c in reader.connections]
    except Exception as exc:  # noqa: BLE001 - whatever rosbags raises, the recovery reader tries
        log.info("rosbags cannot open %s (%s: %s); reading it with the recovery reader", f,
                 type(exc).__name__, exc)
        return None


def _rosbags_messages(f: Path, storage: str, want: set[str] | None,
                      problem: recover.Problem) -> Iterator[recover.MessageRow]:
    """Messages of one storage file through rosbags. If rosbags raises while reading (a damaged
    chunk or page), the recovery reader takes over after the messages already yielded: it
    follows the same order and reads up to the damage itself (rosbags loads the next chunk
    before yielding an equal stamp of the previous one, so it would stop one message early),
    and it records the problem."""
    from rosbags.rosbag2 import Reader

    n = 0
    try:
        with Reader(f) as reader:
            conns = [c for c in reader.connections if want is None or c.topic in want]
            if not conns:  # (an empty selection means "all" to rosbags)
                return
            for conn, t, data in reader.messages(conns):
                yield conn.topic, _msgtype(conn.msgtype), t, data
                n += 1
            return
    except Exception as exc:  # noqa: BLE001 - rosbags' errors on damaged data vary
        log.warning("rosbags stopped reading %s after %d messages (%s: %s); the recovery reader "
                    "reads on", f, n, type(exc).__name__, exc)
    yield from islice(recover.messages(f, storage, want, problem), n, None)
