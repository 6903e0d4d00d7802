"""Reading bags: real rosbag2 bags written by others, and damaged inputs (truncated MCAP at
several offsets, corrupt sqlite3, missing files) — clear BagErrors or partial, usable reads."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from vlm_vpr_ros.bags.messages import IMAGE_TYPES, NAVSATFIX
from vlm_vpr_ros.bags.reader import deserialize, open_bag
from vlm_vpr_ros.bags.writer import bag_files
from vlm_vpr_ros.errors import BagError

BAGS = "data/bags"


# -- real bags (skip without ../shared) ---------------------------------------------------------
def test_event_camera_bag_has_no_images(shared_dir):
    bag = open_bag(shared_dir / BAGS / "event_camera_py_test_events_2")
    assert bag.storage == "mcap"  # metadata.yaml says storage "" : detected from the file
    assert bag.topics["/event_camera/events"].count == 100
    with pytest.raises(BagError, match=r"no sensor_msgs/msg/Image or sensor_msgs/msg/"
                                       r"CompressedImage topic.*the bag has: /event_camera/"
                                       r"events \[event_camera_msgs/msg/EventPacket, 100 msgs\]"):
        bag.find_topic(IMAGE_TYPES, None, "camera images")
    assert sum(1 for _ in bag.messages()) == 100 and bag.complete


def test_event_camera_bag_cli_error(shared_dir, demo_map, caplog, tmp_path):
    from vlm_vpr_ros.cli import main

    rc = main(["evaluate-bag", str(shared_dir / BAGS / "event_camera_py_test_events_2"),
               "--map", str(demo_map), "--out", str(tmp_path / "ev")])
    assert rc == 2
    assert "/event_camera/events" in caplog.text and not (tmp_path / "ev").exists()


def test_rosbag2_talker_reads_like_mcap_ros2(shared_dir):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = shared_dir / BAGS / "rosbag2_talker"
    bag = open_bag(path)
    assert {n: (t.type, t.count) for n, t in bag.topics.items()} == {
        "/topic": ("std_msgs/msg/String", 10), "/rosout": ("rcl_interfaces/msg/Log", 10),
        "/parameter_events": ("rcl_interfaces/msg/ParameterEvent", 0)}
    ours = [(m.log_time_ns, deserialize(m).data) for m in bag.messages(["/topic"])]
    with open(path / "talker.mcap", "rb") as fh:  # (rosbags 0.11 yields nothing for this bag)
        ref = [(m.log_time, msg.data) for _, _, m, msg in make_reader(
            fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages(topics=["/topic"])]
    assert ours == ref and len(ours) == 10 and ours[0][1] == "Hello, world! 0"
    single = open_bag(path / "talker.mcap")  # a lone .mcap file reads too
    assert [m.data for m in single.messages(["/topic"])] == \
        [m.data for m in bag.messages(["/topic"])]


def test_sqlite3_bag_gps_ground_truth(shared_dir):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from vlm_vpr_ros.bags.frames import read_ground_truth

    path = shared_dir / BAGS / "stinger_localization_bag_sqlite3"
    bag = open_bag(path)
    assert bag.storage == "sqlite3"
    topic = bag.find_topic((NAVSATFIX,), None, "ground truth").name
    assert topic == "/gps/fix"
    gt = read_ground_truth(bag, topic)
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        conns = [c for c in r.connections if c.topic == "/gps/fix"]
        ref = sorted((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m.latitude,
                      m.longitude) for m in (r.deserialize(raw, c.msgtype)
                                             for c, _, raw in r.messages(connections=conns)))
    assert list(zip(gt.stamps, gt.lat, gt.lon)) == ref and len(ref) == 9
    assert all(33.7 < a < 33.8 and -84.45 < b < -84.35 for a, b in zip(gt.lat, gt.lon))


# -- damaged inputs -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def raw_bag(demo_data, tmp_path_factory) -> Path:
    """Five raw 682x512 frames: each ~1 MB message gets its own MCAP chunk."""
    from vlm_vpr_ros.bags.make import make_bag

    root = tmp_path_factory.mktemp("rawbag")
    lines = (demo_data / "coords.csv").read_text().splitlines()[:6]
    (root / "c.csv").write_text("\n".join(lines) + "\n")
    make_bag(demo_data / "images", root / "c.csv", root / "bag", rate_hz=2.0,
             start_time_ns=10**18, progress=False)
    return root / "bag"


@pytest.mark.parametrize("fraction", [0.0005, 0.3, 0.62, -64])  # < 0: bytes cut off the end
def test_truncated_mcap_keeps_what_was_read(raw_bag, tmp_path, fraction):
    full = [(m.topic, m.log_time_ns, m.data) for m in open_bag(raw_bag).messages()]
    src = bag_files(raw_bag)[0]
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:int(len(data) * fraction)] if fraction > 0 else data[:fraction])
    bag = open_bag(cut)  # header intact: opens, reports the damage
    got = [(m.topic, m.log_time_ns, m.data) for m in bag.messages()]
    assert not bag.complete and "truncated" in " ".join(bag.problems)
    assert bag.recovered == [cut]  # rosbags refuses a truncated MCAP: the recovery reader read
    assert got == full[:len(got)]  # an exact prefix: nothing garbled
    if fraction < 0:
        assert len(got) == len(full)  # only the summary was lost
    elif fraction > 0.2:
        assert 0 < len(got) < len(full)
    else:
        assert got == [] and bag.topics == {}
        with pytest.raises(BagError, match=r"no sensor_msgs.*the bag has: \(no topics\)"):
            bag.find_topic(IMAGE_TYPES, None, "camera images")


def test_mcap_cut_inside_magic_and_garbage(tmp_path, raw_bag):
    src = bag_files(raw_bag)[0].read_bytes()
    for name, payload in [("short.mcap", src[:4]), ("zero.mcap", b""),
                          ("text.mcap", b"hello, not a bag\n" * 10)]:
        (tmp_path / name).write_bytes(payload)
        with pytest.raises(BagError, match="not an MCAP file"):
            open_bag(tmp_path / name)


def _with_crcs(src: Path, dst: Path, compression: str) -> Path:
    """The MCAP rewritten by the mcap library's writer, which stores chunk CRCs (as rosbag2
    does; rosbags writes 0 = "not computed")."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with open(src, "rb") as fh, open(dst, "wb") as out:
        summary = make_reader(fh).get_summary()
        w = Writer(out, compression=CompressionType[compression.upper()])
        w.start(profile="ros2")
        for sid, sch in summary.schemas.items():
            w.register_schema(sch.name, sch.encoding, sch.data)  # ids in the same order
        for cid, ch in summary.channels.items():
            w.register_channel(ch.topic, ch.message_encoding, ch.schema_id, ch.metadata)
        fh.seek(0)
        for _, ch, m in make_reader(fh).iter_messages():
            w.add_message(ch.id, m.log_time, m.data, m.publish_time)
        w.finish()
    return dst


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_corrupt_chunk_is_detected(tmp_path, raw_bag, compression):
    src = _with_crcs(bag_files(raw_bag)[0], tmp_path / "crc.mcap", compression)
    assert sum(1 for _ in open_bag(src).messages()) == 10
    data = bytearray(src.read_bytes())
    data[len(data) // 2] ^= 0xFF  # flip a byte inside a chunk: its CRC no longer matches
    (tmp_path / "flip.mcap").write_bytes(bytes(data))
    bag = open_bag(tmp_path / "flip.mcap")
    n = sum(1 for _ in bag.messages())
    assert not bag.complete and n < 10


def test_sqlite3_damage(tmp_path, shared_dir):
    garbage = tmp_path / "junk.db3"
    garbage.write_bytes(b"SQLite format 3\x00" + b"\x00" * 50)
    with pytest.raises(BagError, match="not a readable rosbag2 sqlite3 file"):
        open_bag(garbage)
    src = shared_dir / BAGS / "stinger_localization_bag_sqlite3" / "localization_bag_0.db3"
    half = tmp_path / "half.db3"
    half.write_bytes(src.read_bytes()[:len(src.read_bytes()) // 2])
    try:
        bag = open_bag(half)
    except BagError as exc:
        assert "half.db3" in str(exc)
    else:
        list(bag.messages())  # whatever is readable, without raising


def test_missing_paths(tmp_path, raw_bag):
    with pytest.raises(BagError, match="bag not found"):
        open_bag(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match="no .mcap or .db3 file"):
        open_bag(tmp_path / "empty")
    copy = tmp_path / "copy"
    shutil.copytree(raw_bag, copy)
    (copy / bag_files(raw_bag)[0].name).unlink()
    with pytest.raises(BagError, match="lists missing file"):
        open_bag(copy)
    (tmp_path / "x.bag").write_bytes(b"#ROSBAG V2.0\n")
    with pytest.raises(BagError, match="supported: rosbag2 MCAP"):
        open_bag(tmp_path / "x.bag")
