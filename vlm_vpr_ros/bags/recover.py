"""The hand-written part of bag reading: files that rosbags refuses, and the rest of a file
after rosbags stopped inside it.

:mod:`vlm_vpr_ros.bags.reader` reads every storage file through rosbags first. rosbags opens a
file only when it is whole: a truncated MCAP (no footer, no summary) or an MCAP with another
profile raises ``ReaderError`` on open, and a rosbags error means "nothing from this file"; an
error inside a file ends rosbags' read there, possibly before intact messages of equal stamp.
The functions here read such a file **up to the damage** instead, so a half-recorded drive
still gives its first part:

* MCAP with a readable summary: the ``mcap`` library's indexed reader, messages in log-time
  order with ties in file position order (the same rule as rosbags), stopping at a damaged
  chunk;
* MCAP without a usable summary (truncated, never closed): one sequential pass over the
  records with the ``mcap`` library's ``StreamReader`` in file order (recording order), up to
  the last complete record;
* sqlite3: a plain read-only query ``ORDER BY timestamp, id`` (rosbags' ``ORDER BY timestamp``
  only gives this tie order when the ``timestamp`` index exists, see ``reader.py``).

Reading stops at the first exception of any kind (the ``mcap`` library, zstd, lz4 and
``struct`` each raise their own on damaged bytes), after everything before it was yielded.
What went wrong is reported through the ``problem`` callback (the bag's ``problems`` list).
Nothing here knows the reader's classes: topics come back as plain tuples
``(name, type, count, serialization_format, offered_qos_profiles)`` and messages as
``(topic, type, log_time_ns, data)``.
"""

from __future__ import annotations

import sqlite3
from contextlib import closing
from pathlib import Path
from typing import Any, Callable, Iterator

from vlm_vpr_ros.errors import BagError

Problem = Callable[[str], None]
TopicRow = tuple[str, str, int, str, Any]
MessageRow = tuple[str, str, int, bytes]

def list_topics(f: Path, storage: str, problem: Problem) -> list[TopicRow]:
    """The topics of one storage file; BagError if it is not a bag file at all."""
    return _list_mcap(f, problem) if storage == "mcap" else _list_db3(f)


def messages(f: Path, storage: str, want: set[str] | None,
             problem: Problem) -> Iterator[MessageRow]:
    """Messages of ``want`` topics (all when None) up to the first damage."""
    return _iter_mcap(f, want, problem) if storage == "mcap" else _iter_db3(f, want, problem)


# -- MCAP ---------------------------------------------------------------------------------------
def _summary(f: Path) -> Any:
    from mcap.reader import make_reader

    with open(f, "rb") as fh:
        try:
            return make_reader(fh).get_summary()
        except Exception:  # noqa: BLE001 - no usable summary: read the records one by one
            return None


def _list_mcap(f: Path, problem: Problem) -> list[TopicRow]:
    with open(f, "rb") as fh:
        head = fh.read(8)
    if head[:5] != b"\x89MCAP":
        raise BagError(f"{f}: not an MCAP file (bad magic {head!r}); empty or corrupt")
    summary = _summary(f)
    if summary is not None:
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        return [(ch.topic, getattr(summary.schemas.get(ch.schema_id), "name", ""),
                 counts.get(cid, 0), ch.message_encoding, ch.metadata.get("offered_qos_profiles"))
                for cid, ch in summary.channels.items()]
    problem(f"{f.name}: no MCAP summary (file truncated or not closed); reading it "
            "sequentially, messages after the damage are lost")
    counts_by_topic: dict[str, int] = {}
    channels: dict[str, tuple[str, str, Any]] = {}
    for kind, topic, type_, a, b in _stream(f, None, problem):
        if kind == "channel":
            channels.setdefault(topic, (type_, a, b))
        else:
            counts_by_topic[topic] = counts_by_topic.get(topic, 0) + 1
    return [(topic, type_, counts_by_topic.get(topic, 0), enc, qos)
            for topic, (type_, enc, qos) in channels.items()]


def _stream(f: Path, want: set[str] | None, problem: Problem) -> Iterator[tuple]:
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
        except Exception as exc:  # noqa: BLE001 - whatever damaged data raises ends the file
            problem(f"{f.name}: damaged or truncated MCAP after the last complete record "
                    f"({type(exc).__name__}: {exc}); later messages are lost")


def _iter_mcap(f: Path, want: set[str] | None, problem: Problem) -> Iterator[MessageRow]:
    from mcap.reader import make_reader

    if _summary(f) is None:
        for kind, topic, type_, t, data in _stream(f, want, problem):
            if kind == "message":
                yield topic, type_, int(t), data
        return
    with open(f, "rb") as fh:
        try:
            reader = make_reader(fh, validate_crcs=True)
            for schema, ch, m in reader.iter_messages(topics=sorted(want) if want else None):
                yield ch.topic, schema.name if schema else "", int(m.log_time), bytes(m.data)
        except Exception as exc:  # noqa: BLE001 - as above (mcap, zstd, lz4, struct errors)
            problem(f"{f.name}: corrupt MCAP data ({type(exc).__name__}: {exc}); "
                    "later messages are lost")


# -- sqlite3 ------------------------------------------------------------------------------------
def connect(f: Path) -> sqlite3.Connection:
    """A read-only connection that never writes a journal next to the bag."""
    return sqlite3.connect(f"file:{f.resolve()}?mode=ro&immutable=1", uri=True)


def _list_db3(f: Path) -> list[TopicRow]:
    try:
        with closing(connect(f)) as db:
            rows = db.execute("SELECT id, name, type, serialization_format, "
                              "offered_qos_profiles FROM topics").fetchall()
            counts = dict(db.execute("SELECT topic_id, COUNT(*) FROM messages "
                                     "GROUP BY topic_id").fetchall())
    except sqlite3.Error as exc:
        raise BagError(f"{f}: not a readable rosbag2 sqlite3 file ({exc})") from None
    return [(name, type_, int(counts.get(tid, 0)), fmt, qos)
            for tid, name, type_, fmt, qos in rows]


def _iter_db3(f: Path, want: set[str] | None, problem: Problem) -> Iterator[MessageRow]:
    try:
        db = connect(f)
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
            yield name, type_, int(t), bytes(data)
    except sqlite3.Error as exc:
        problem(f"{f.name}: corrupt sqlite3 data ({exc}); later messages are lost")
    finally:
        db.close()
