"""``vlm-vpr replay`` against a real subscriber in another process (own ROS domain, localhost).

The subscriber takes raw CDR with ``raw=True`` and stamps each arrival; the test compares the
bytes with what the bag holds (per topic, in order) and the arrival spacing with the recorded
spacing divided by ``--rate``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from vlm_vpr_ros.bags.make import make_bag
from vlm_vpr_ros.bags.reader import open_bag

DOMAIN_ID = 47  # this file's own domain (helpers' tests use 20-59, one each)
FRAMES, RATE_HZ = 8, 4.0

SUBSCRIBER = r"""
import json, sys, time
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Image, NavSatFix

out, expected, deadline_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
ctx = Context()
rclpy.init(context=ctx)
node = Node("replay_probe", context=ctx)
got = []
def cb(topic):
    return lambda data: got.append([topic, time.monotonic(), data.hex()])
node.create_subscription(Image, "/probe/image_raw", cb("/camera/image_raw"),
                         QoSProfile(depth=100), raw=True)
node.create_subscription(NavSatFix, "/gps/fix", cb("/gps/fix"), QoSProfile(depth=100),
                         raw=True)
ex = SingleThreadedExecutor(context=ctx)
ex.add_node(node)
end = time.monotonic() + deadline_s
while len(got) < expected and time.monotonic() < end:
    ex.spin_once(timeout_sec=0.05)
json.dump(got, open(out, "w"))
node.destroy_node()
ctx.try_shutdown()
"""


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("replay")
    rng = np.random.default_rng(3)
    rows = ["file,lat,lon"]
    for i in range(FRAMES):
        img = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
        cv2.imwrite(str(root / f"f{i}.png"), img)
        rows.append(f"f{i}.png,{45 + i * 0.01},{7 + i * 0.01}")
    (root / "coords.csv").write_text("\n".join(rows) + "\n")
    bag = root / "bag"
    make_bag(root, root / "coords.csv", bag, rate_hz=RATE_HZ, start_time_ns=10**18,
             progress=False)
    return bag


def _env() -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


def _replay_into_probe(probe: str, probe_args: list[str], out: Path,
                       replay_args: list[str]) -> tuple[object, str]:
    """Start the probe script (it writes ``out``), run ``vlm-vpr replay`` to completion, wait
    for the probe; (the probe's JSON, replay's stdout)."""
    sub = subprocess.Popen([sys.executable, "-c", probe, str(out), *probe_args], env=_env())
    try:
        rep = subprocess.run([sys.executable, "-m", "vlm_vpr_ros.cli", "replay", *replay_args,
                              "--wait-subscribers", "30"],
                             env=_env(), capture_output=True, text=True, timeout=90)
        sub.wait(timeout=60)
    finally:
        if sub.poll() is None:
            sub.kill()
    assert rep.returncode == 0, rep.stderr
    return json.loads(out.read_text()), rep.stdout


def _replay(bag: Path, rate: float, tmp: Path) -> tuple[list, str]:
    return _replay_into_probe(SUBSCRIBER, [str(2 * FRAMES), "40"], tmp / f"got_{rate}.json",
                              [str(bag), "--rate", str(rate),
                               "--remap", "/camera/image_raw:=/probe/image_raw"])


def _check_content(bag: Path, got: list) -> dict:
    expected: dict[str, list[str]] = {}
    for m in open_bag(bag).messages():
        expected.setdefault(m.topic, []).append(m.data.hex())
    received: dict[str, list[str]] = {}
    times: dict[str, list[float]] = {}
    for topic, t, data in got:
        received.setdefault(topic, []).append(data)
        times.setdefault(topic, []).append(t)
    assert sorted(received) == sorted(expected)
    for topic, sent in expected.items():  # every message, in recorded order per topic
        assert len(received[topic]) == len(sent), topic
        for a, b in zip(sent, received[topic]):
            # byte-identical CDR; DDS may pad the payload to a multiple of 4 bytes
            assert b[:len(a)] == a and len(b) - len(a) < 8, topic
    return times


def test_replay_rate_1_keeps_recorded_timing(small_bag, tmp_path):
    got, stdout = _replay(small_bag, 1.0, tmp_path)
    times = _check_content(small_bag, got)
    gaps = np.diff(times["/camera/image_raw"])
    period = 1.0 / RATE_HZ
    assert np.median(gaps) == pytest.approx(period, abs=0.08)
    span = times["/camera/image_raw"][-1] - times["/camera/image_raw"][0]
    assert span == pytest.approx((FRAMES - 1) * period, abs=0.5)
    assert f"replayed {2 * FRAMES} messages" in stdout


def test_replay_rate_10_is_faster(small_bag, tmp_path):
    got, _ = _replay(small_bag, 10.0, tmp_path)
    times = _check_content(small_bag, got)
    span = times["/camera/image_raw"][-1] - times["/camera/image_raw"][0]
    recorded = (FRAMES - 1) / RATE_HZ
    assert span < recorded / 3  # 10x faster: 0.175 s instead of 1.75 s, with slack


def test_replay_rejects_unknown_topic(small_bag):
    from vlm_vpr_ros.bags.replay import ReplayConfig, select_topics
    from vlm_vpr_ros.errors import BagError

    with pytest.raises(BagError, match=r"/nope.*the bag has: .*/gps/fix"):
        select_topics(open_bag(small_bag), ReplayConfig(topics=["/nope"]))


def test_parse_remaps():
    from vlm_vpr_ros.bags.replay import parse_remaps
    from vlm_vpr_ros.errors import ConfigError

    assert parse_remaps(["/a:=/b", "/c:=/d/e"]) == {"/a": "/b", "/c": "/d/e"}
    with pytest.raises(ConfigError, match="FROM:=TO"):
        parse_remaps(["/a=/b"])


CLOCK_PROBE = r"""
import json, sys, time
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import NavSatFix

out, expected, deadline_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
ctx = Context()
rclpy.init(context=ctx)
node = Node("clock_probe", context=ctx)
clocks, fixes = [], []
ns = lambda t: t.sec * 1_000_000_000 + t.nanosec
node.create_subscription(Clock, "/clock", lambda m: clocks.append(ns(m.clock)),
                         QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
node.create_subscription(NavSatFix, "/gps/fix", lambda m: fixes.append(ns(m.header.stamp)),
                         QoSProfile(depth=100))
ex = SingleThreadedExecutor(context=ctx)
ex.add_node(node)
end = time.monotonic() + deadline_s
while len(fixes) < expected and time.monotonic() < end:
    ex.spin_once(timeout_sec=0.05)
t = time.monotonic() + 0.3
while time.monotonic() < t:
    ex.spin_once(timeout_sec=0.05)
json.dump({"clocks": clocks, "fixes": fixes}, open(out, "w"))
node.destroy_node()
ctx.try_shutdown()
"""


def test_replay_clock_publishes_the_bag_time(small_bag, tmp_path):
    """--clock: /clock carries the bag's log time (from its first stamp, never past the last
    message + linger, non-decreasing) at about the requested rate."""
    got, _ = _replay_into_probe(CLOCK_PROBE, [str(FRAMES), "40"], tmp_path / "clock.json",
                                [str(small_bag), "--clock", "50", "--topics", "/gps/fix"])
    stamps = [m.log_time_ns for m in open_bag(small_bag).messages(["/gps/fix"])]
    assert got["fixes"] == stamps
    clocks = got["clocks"]
    span_s = (stamps[-1] - stamps[0]) / 1e9  # 1.75 s of bag time at rate 1
    assert len(clocks) >= 0.5 * 50 * span_s, len(clocks)
    assert clocks == sorted(clocks)
    assert clocks[0] >= stamps[0] and clocks[-1] <= stamps[-1] + int(0.6e9)
    assert set(stamps) <= set(clocks)  # announced right before each message
