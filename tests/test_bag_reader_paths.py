"""The two reading paths of bags/reader.py give the same messages in the same order: intact
MCAP and sqlite3 bags read through rosbags and through the hand-written recovery reader
(``open_bag(..., recovery=True)``) against the order rule computed from what was written
(log time, then write order), with equal stamps across topics and within a topic, stamps
written out of order, and MCAP chunk boundaries between equal stamps."""

from __future__ import annotations

import shutil
import sqlite3
import struct
from pathlib import Path

import pytest

from vlm_vpr_ros.bags.reader import open_bag
from vlm_vpr_ros.bags.writer import BagWriter, bag_files

STRING = "std_msgs/msg/String"
TOPICS = ("/c", "/a", "/b")  # written in this order at equal stamps: not alphabetical


def _cdr_string(text: str) -> bytes:
    """A std_msgs/String as CDR (little-endian header, length incl. NUL, bytes, NUL)."""
    raw = text.encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(raw)) + raw


def _plan() -> list[tuple[str, int, bytes]]:
    """(topic, log time, CDR) in write order: triples sharing a stamp across topics, pairs
    sharing a stamp on one topic, late messages stamped before earlier ones, and ~200 kB
    messages so that rosbags' 1 MiB chunks split runs of equal stamps."""
    out = []
    base = 1_700_000_000_000_000_000
    for i in range(120):
        t = base + (i // 3) * 1_000_000
        if i % 11 == 5:
            t -= 7_000_000  # out of order: earlier than messages already written
        pad = "x" * (200_000 if i % 9 == 0 else 8)
        topic = TOPICS[(i + i // 3) % 3]
        out.append((topic, t, _cdr_string(f"{i} {pad}")))
        if i % 10 == 0:  # same topic, same stamp, different payload
            out.append((topic, t, _cdr_string(f"{i} twin")))
    return out


def _expected(plan: list[tuple[str, int, bytes]]) -> list[tuple[str, str, int, bytes]]:
    order = sorted(range(len(plan)), key=lambda k: (plan[k][1], k))
    return [(plan[k][0], STRING, plan[k][1], plan[k][2]) for k in order]


@pytest.fixture(scope="module", params=["mcap", "sqlite3"])
def written(request, tmp_path_factory) -> tuple[Path, list]:
    plan = _plan()
    path = tmp_path_factory.mktemp(f"paths_{request.param}") / "bag"
    with BagWriter(path, storage=request.param) as w:
        for topic in sorted(TOPICS):
            w.add_topic(topic, STRING)
        for topic, t, data in plan:
            w.write(topic, data, t)
    return path, plan


def _read(bag, topics=None) -> list[tuple[str, str, int, bytes]]:
    return [(m.topic, m.type, m.log_time_ns, m.data) for m in bag.messages(topics)]


def test_rosbags_and_recovery_read_the_same(written):
    path, plan = written
    expected = _expected(plan)
    assert len({t for _, t, _ in plan}) < len(plan)  # equal stamps are there,
    assert expected != [(p[0], STRING, p[1], p[2]) for p in plan]  # written out of order,
    assert expected != sorted(expected, key=lambda e: (e[2], e[0]))  # ties not by name
    fast, slow = open_bag(path), open_bag(path, recovery=True)
    assert fast.recovered == [] and slow.recovered == bag_files(path)
    got_fast, got_slow = _read(fast), _read(slow)
    assert got_fast == expected and got_slow == expected
    assert fast.complete and slow.complete
    assert fast.topics == slow.topics
    assert {n: t.count for n, t in fast.topics.items()} == \
        {n: sum(1 for p in plan if p[0] == n) for n in TOPICS}
    assert fast.topics["/a"].qos[0]["reliability"] == "reliable"  # the writer's default QoS
    for subset in (["/a"], ["/b", "/c"]):  # selections keep the rule too
        want = [e for e in expected if e[0] in subset]
        assert _read(fast, subset) == want and _read(slow, subset) == want


def test_mcap_runs_of_equal_stamps_span_chunks(written):
    """The MCAP has several chunks with overlapping times, so the tie rule is exercised
    across chunks, not only inside one."""
    path, plan = written
    if not path.joinpath("bag.mcap").exists():
        pytest.skip("MCAP only")
    from mcap.reader import make_reader

    with open(path / "bag.mcap", "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes
    assert len(chunks) >= 3
    assert any(a.message_end_time >= b.message_start_time for a, b in zip(chunks, chunks[1:]))


def test_sqlite3_without_timestamp_index_uses_recovery(written, tmp_path):
    """Without the index rosbags' ORDER BY timestamp has no stated tie order: such a file is
    read by the recovery reader (ORDER BY timestamp, id), with the same result."""
    path, plan = written
    if not path.joinpath("bag.db3").exists():
        pytest.skip("sqlite3 only")
    copy = tmp_path / "noindex"
    shutil.copytree(path, copy)
    con = sqlite3.connect(copy / "bag.db3")
    con.execute("DROP INDEX timestamp_idx")
    con.commit()
    con.close()
    bag = open_bag(copy)
    assert bag.recovered == [copy / "bag.db3"]
    assert _read(bag) == _expected(plan) and bag.complete


def test_damaged_chunk_read_up_to_the_damage(tmp_path):
    """A CRC-failing chunk whose first stamp equals the last stamp of the chunk before: rosbags
    loads that chunk before yielding the equal stamp, so the recovery reader takes over and
    the read is every message of the intact chunks before it, exactly."""
    from mcap.reader import breakup_chunk
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, Writer

    src = tmp_path / "crc.mcap"
    plan = [("/a" if i % 2 else "/b", 10**18 + (i // 2) * 10**6, _cdr_string(str(i) * (i % 7 + 1)
                                                                            * 40))
            for i in range(400)]
    with open(src, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE, chunk_size=3000)  # stores chunk CRCs
        w.start(profile="ros2")
        sid = w.register_schema(STRING, "ros2msg", b"string data")
        chans = {t: w.register_channel(t, "cdr", sid) for t in ("/a", "/b")}
        for topic, t, data in plan:
            w.add_message(chans[topic], t, data, t)
        w.finish()
    with open(src, "rb") as fh:  # (offset, first stamp, messages before it) per chunk
        chunks, before, last_t = [], 0, None
        for rec in StreamReader(fh, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                msgs = [r for r in breakup_chunk(rec) if isinstance(r, Message)]
                chunks.append((msgs[0].log_time, before, last_t))
                before, last_t = before + len(msgs), msgs[-1].log_time
    k = next(i for i, (first, _, prev_last) in enumerate(chunks) if i > 2 and first == prev_last)
    data = bytearray(src.read_bytes())
    marker = plan[chunks[k][1] + 1][2]  # a message inside chunk k: flip a byte of it
    data[data.index(marker) + 10] ^= 0xFF
    (tmp_path / "flip.mcap").write_bytes(bytes(data))
    expected = _expected(plan)[:chunks[k][1]]
    for recovery in (False, True):
        bag = open_bag(tmp_path / "flip.mcap", recovery=recovery)
        assert bag.recovered == ([tmp_path / "flip.mcap"] if recovery else [])
        assert _read(bag) == expected and not bag.complete
        assert "corrupt MCAP data" in " ".join(bag.problems)
