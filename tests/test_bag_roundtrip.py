"""``bag make`` round trip: the bag reads back identically through three independent readers
(mcap-ros2-support decoding from the stored schema text, rosbags from metadata.yaml + its own
CDR decoder, and our reader + rclpy), its type hashes are the ones ROS 2 itself reports and its
message definitions parse to the ones the installed message packages (and rosbag2's own
recording) hold. Both storages (MCAP, sqlite3) and zstd chunks are covered."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from vlm_vpr_ros.bags.make import make_bag
from vlm_vpr_ros.bags.reader import RawMessage, deserialize, open_bag
from vlm_vpr_ros.bags.writer import bag_files
from vlm_vpr_ros.errors import BagError, ConfigError, DataError, OutputError
from vlm_vpr_ros.files.images import load_image

START = 1_700_000_000_250_000_000
N = 5


@pytest.fixture(scope="module")
def subset(demo_data, tmp_path_factory) -> tuple[Path, list[tuple[str, float, float]]]:
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv

    rows = read_coords_csv(demo_data / "coords.csv")[:N]
    csv = tmp_path_factory.mktemp("subset") / "coords.csv"
    csv.write_text("file,lat,lon\n" + "".join(f"{f},{a!r},{b!r}\n" for f, a, b in rows))
    return csv, rows


@pytest.fixture(scope="module", params=[False, True], ids=["raw", "compressed"])
def made(request, demo_data, subset, tmp_path_factory):
    csv, rows = subset
    out = tmp_path_factory.mktemp("made") / ("cbag" if request.param else "rbag")
    info = make_bag(demo_data / "images", csv, out, rate_hz=4.0, compressed=request.param,
                    start_time_ns=START, progress=False)
    return out, info, rows, request.param


def _stamps() -> list[int]:
    return [START + i * 250_000_000 for i in range(N)]


def test_layout_and_metadata(made):
    out, info, rows, compressed = made
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["metadata.yaml", "frames.csv", f"{out.name}.mcap"])
    assert bag_files(out) == [out / f"{out.name}.mcap"]
    meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    _assert_jazzy(out / f"{out.name}.mcap", meta)
    assert meta["custom_data"]["writer"].startswith("vlm_vpr_ros ")
    assert meta["message_count"] == 2 * N
    assert meta["starting_time"]["nanoseconds_since_epoch"] == START
    assert meta["duration"]["nanoseconds"] == (N - 1) * 250_000_000
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    img = "/camera/image_raw/compressed" if compressed else "/camera/image_raw"
    assert set(topics) == {img, "/gps/fix"} and info["image_topic"] == img
    for t in topics.values():
        assert t["message_count"] == N
        assert t["topic_metadata"]["serialization_format"] == "cdr"
        assert t["topic_metadata"]["type_description_hash"].startswith("RIHS01_")
        assert t["topic_metadata"]["offered_qos_profiles"][0]["reliability"] == "reliable"


def test_three_readers_agree(made, demo_data):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out, info, rows, compressed = made
    mcap_file = bag_files(out)[0]
    with open(mcap_file, "rb") as fh:  # decodes with the schema text stored in the file
        via_mcap = [(ch.topic, m.log_time, msg) for _, ch, m, msg in make_reader(
            fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    with AnyReader([out], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        via_rosbags = [(c.topic, t, r.deserialize(raw, c.msgtype)) for c, t, raw in r.messages()]
    via_rclpy = [(m.topic, m.log_time_ns, deserialize(m)) for m in open_bag(out).messages()]
    assert len(via_mcap) == len(via_rosbags) == len(via_rclpy) == 2 * N
    stamps = _stamps()
    for reader in (via_mcap, via_rosbags, via_rclpy):
        fixes = [(t, m) for topic, t, m in reader if topic == "/gps/fix"]
        frames = [(t, m) for topic, t, m in reader if topic == info["image_topic"]]
        assert [t for t, _ in fixes] == stamps and [t for t, _ in frames] == stamps
        for (t, fix), (_file, lat, lon) in zip(fixes, rows):
            assert (fix.header.stamp.sec, fix.header.stamp.nanosec) == divmod(t, 10**9)
            assert fix.latitude == lat and fix.longitude == lon  # exact float64 round trip
            assert fix.status.status == 0 and math.isnan(fix.altitude)
        for (t, img), (f, _, _) in zip(frames, rows):
            assert (img.header.stamp.sec, img.header.stamp.nanosec) == divmod(t, 10**9)
            assert img.header.frame_id == "camera"
            if compressed:
                assert img.format == "jpeg"
                assert bytes(img.data) == (demo_data / "images" / f).read_bytes()
            else:
                rgb = load_image(demo_data / "images" / f)
                assert (img.height, img.width, img.encoding, img.step) == (
                    rgb.shape[0], rgb.shape[1], "rgb8", rgb.shape[1] * 3)
                assert bytes(img.data) == rgb.tobytes()


def test_type_hashes_match_ros(made):
    """metadata.yaml hashes == rosbags' independent RIHS01 computation == what rmw reports for
    a live publisher of the type."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rosbags.typesys import Stores, get_typestore

    from vlm_vpr_ros.bags.messages import message_class

    out, *_ = made
    meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    ours = {t["topic_metadata"]["type"]: t["topic_metadata"]["type_description_hash"]
            for t in meta["topics_with_message_count"]}
    store = get_typestore(Stores.ROS2_JAZZY)
    assert ours == {k: store.hash_rihs01(k) for k in ours}
    ctx = Context()
    rclpy.init(context=ctx, domain_id=49)
    try:
        node = Node("hash_probe", context=ctx, start_parameter_services=False)
        live = {}
        for i, type_name in enumerate(ours):
            node.create_publisher(message_class(type_name), f"/hash_probe_{i}", 1)
            info = node.get_publishers_info_by_topic(f"/hash_probe_{i}")
            live[type_name] = str(info[0].topic_type_hash)
        node.destroy_node()
    finally:
        ctx.try_shutdown()
    assert ours == live


def _definitions(text: str, root: str) -> dict:
    """A ros2msg schema (root text, then ``MSG: pkg/Type`` sections) parsed per type."""
    from rosbags.typesys import get_types_from_msg

    first, *rest = text.split("=" * 80 + "\n")
    out = dict(get_types_from_msg(first, root))
    for section in rest:
        head, _, body = section.partition("\n")
        parts = head.removeprefix("MSG: ").split("/")  # pkg/Type (or pkg/msg/Type)
        pkg, name = parts[0], parts[-1]
        out.update(get_types_from_msg(body, f"{pkg}/msg/{name}"))
    return out


def test_definitions_match_the_installed_messages(made):
    """Every type section of the bag's schemas, parsed, equals the installed ``.msg`` file of
    that type (what rosbag2 stores, comments aside), and the root types are the bag's types."""
    import sys

    from mcap.reader import make_reader

    out, *_ = made
    with open(bag_files(out)[0], "rb") as fh:
        schemas = {s.name: s.data.decode() for s in make_reader(fh).get_summary().schemas.values()}
    meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert set(schemas) == {t["topic_metadata"]["type"] for t in meta["topics_with_message_count"]}
    share = Path(sys.prefix) / "share"
    checked = set()
    for root, text in schemas.items():
        for type_name, parsed in _definitions(text, root).items():
            pkg, _, name = type_name.split("/")
            msg = (share / pkg / "msg" / f"{name}.msg").read_text()
            assert parsed == _definitions(msg, type_name)[type_name], type_name
            checked.add(type_name)
    assert {"std_msgs/msg/Header", "builtin_interfaces/msg/Time"} <= checked


def test_definitions_match_a_rosbag2_recording(shared_dir):
    """The definitions rosbags generates parse to the ones rosbag2 recorded in its test bag."""
    from mcap.reader import make_reader

    from vlm_vpr_ros.bags.writer import typestore

    with open(shared_dir / "data/bags/rosbag2_talker/talker.mcap", "rb") as fh:
        schemas = {s.name: s.data.decode() for s in make_reader(fh).get_summary().schemas.values()}
    for name in ("std_msgs/msg/String", "rcl_interfaces/msg/ParameterEvent"):
        ours, _ = typestore().generate_msgdef(name, ros_version=2)
        assert _definitions(ours, name) == _definitions(schemas[name], name)


def _assert_jazzy(storage_file: Path, meta: dict) -> None:
    """The bag names the ROS distribution its messages are from (not the writing library), in
    metadata.yaml and in the copy inside the storage file (sqlite3: also its schema table);
    read with the mcap library and sqlite3 directly."""
    import sqlite3

    assert meta["ros_distro"] == "jazzy"
    if storage_file.suffix == ".db3":
        con = sqlite3.connect(storage_file)
        try:
            assert con.execute("SELECT ros_distro FROM schema").fetchall() == [("jazzy",)]
            (inner,), = con.execute("SELECT metadata FROM metadata").fetchall()
        finally:
            con.close()
    else:
        from mcap.reader import make_reader

        with storage_file.open("rb") as f:
            records = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
        inner = records["rosbag2"]["serialized_metadata"]
    assert yaml.safe_load(inner)["ros_distro"] == "jazzy"


def test_sqlite3_storage_and_zstd_chunks(demo_data, subset, tmp_path):
    """The same frames as a sqlite3 bag and as a zstd-compressed MCAP read back identically
    (our reader and rosbags), with the storage rosbag2 names in metadata.yaml."""
    from rosbags.highlevel import AnyReader

    from vlm_vpr_ros.bags.writer import typestore

    csv, rows = subset
    bags = {}
    for storage, compression in (("mcap", "none"), ("sqlite3", "none"), ("mcap", "zstd")):
        out = tmp_path / f"{storage}_{compression}"
        make_bag(demo_data / "images", csv, out, rate_hz=4.0, compressed=True,
                 start_time_ns=START, storage=storage, compression=compression, progress=False)
        meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert meta["storage_identifier"] == storage
        assert bag_files(out)[0].suffix == (".db3" if storage == "sqlite3" else ".mcap")
        _assert_jazzy(bag_files(out)[0], meta)
        bag = open_bag(out)
        assert bag.storage == storage and bag.complete
        ours = sorted((m.topic, m.log_time_ns, m.data) for m in bag.messages())
        with AnyReader([out], default_typestore=typestore()) as r:
            theirs = sorted((c.topic, t, bytes(raw)) for c, t, raw in r.messages())
        assert ours == theirs and len(ours) == 2 * N
        # rclpy leaves CDR padding bytes undefined: compare the decoded messages (by repr, as
        # the fixes' NaN altitude never equals itself)
        bags[(storage, compression)] = [(topic, t, repr(deserialize(RawMessage(topic, typ, t,
                                                                               raw))))
                                        for topic, t, raw in ours
                                        for typ in [bag.topics[topic].type]]
    first, *others = bags.values()
    assert all(o == first for o in others)
    plain = bag_files(tmp_path / "mcap_none")[0].stat().st_size
    assert bag_files(tmp_path / "mcap_zstd")[0].stat().st_size < plain
    with pytest.raises(BagError, match="needs --storage mcap"):
        make_bag(demo_data / "images", csv, tmp_path / "bad", storage="sqlite3",
                 compression="zstd", progress=False)
    assert not (tmp_path / "bad").exists()


def test_frames_sidecar_and_no_partial_bag_on_error(made, tmp_path, subset, demo_data):
    out, info, rows, _ = made
    lines = (out / "frames.csv").read_text().splitlines()
    assert lines[0] == "index,stamp_ns,file,lat,lon" and len(lines) == N + 1
    assert lines[1].split(",")[1:3] == [str(START), rows[0][0]]
    with pytest.raises(OutputError, match="already holds a bag; pass --overwrite"):
        make_bag(demo_data / "images", subset[0], out, progress=False)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(BagError, match="no readable image"):
        make_bag(empty, subset[0], tmp_path / "nobag", progress=False)
    assert not (tmp_path / "nobag").exists()
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".nobag")]  # temp removed
    with pytest.raises(ConfigError, match="rate"):
        make_bag(demo_data / "images", subset[0], tmp_path / "x", rate_hz=0, progress=False)
    bad = tmp_path / "bad.csv"
    bad.write_text("name,lat\n")
    with pytest.raises(DataError, match="missing column"):
        make_bag(demo_data / "images", bad, tmp_path / "y", progress=False)


def test_cli_bag_make_and_info(demo_data, subset, tmp_path, capsys):
    from vlm_vpr_ros.cli import main

    out = tmp_path / "clibag"
    assert main(["bag", "make", "--images", str(demo_data / "images"), "--coords",
                 str(subset[0]), "--out", str(out), "--compressed", "--rate", "2",
                 "--topic-prefix", "/front", "--mcap-compression", "zstd"]) == 0
    assert "5 frames on /front/image_raw/compressed + /gps/fix over 2.0 s" in \
        capsys.readouterr().out
    assert main(["bag", "info", str(out), "--json"]) == 0
    import json

    info = json.loads(capsys.readouterr().out)
    assert info["topics"] == {
        "/front/image_raw/compressed": {"type": "sensor_msgs/msg/CompressedImage", "count": 5},
        "/gps/fix": {"type": "sensor_msgs/msg/NavSatFix", "count": 5}}
    assert info["complete"] is True
    arr = np.array([m.log_time_ns for m in open_bag(out).messages(["/gps/fix"])])
    assert (np.diff(arr) == 500_000_000).all()
