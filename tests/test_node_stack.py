"""vlm_vpr_node in a localization stack, over a real ROS 2 graph (rclpy + Fast DDS, the node in
its own process): concurrent relocalize callers during a slow VLM call, a late subscriber of
the transient-local fix and pose, runtime tuning, the debug views. One node serves the module
(a 3 s loopback VLM, on_trigger mode, transient_local outputs, publish_debug)."""

from __future__ import annotations

import math
import re
import time

import cv2
import numpy as np
import pytest

from node_harness import domain_id, image_msg, node_and_client, stamp_of
from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.runtime.metric_frame import UNKNOWN_ANGLE_VAR, MetricFrame

pytestmark = pytest.mark.timeout(180)
QUERY = "546314506564628.jpg"  # Sanluri, Sardinia
TRUTH = (39.55910238557, 8.8888751944543)
NO_FIX, FIX = -1, 0
NODE = "/vlm_vpr_node"
VLM_DELAY_S = 3.0


def _tl_qos():
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture(scope="module")
def rgb(demo_data):
    return load_image(demo_data / "images" / QUERY)


@pytest.fixture(scope="module")
def stack(demo_map, demo_data, tmp_path_factory, rgb):
    from chat_server import ChatServer
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from sensor_msgs.msg import CompressedImage
    from vlm_vpr_interfaces.msg import Candidates

    log = tmp_path_factory.mktemp("node_stack") / "node.log"
    with ChatServer("slow", lat=TRUTH[0] + 0.01, lon=TRUTH[1], delay_s=VLM_DELAY_S) as srv:
        params = {"map_dir": str(demo_map), "prior_provider": "openai",
                  "prior.base_url": srv.base_url, "prior.model": "fixture-model",
                  "prior.max_retries": 0, "prior_timeout_s": 30.0, "mode": "on_trigger",
                  "fix_durability": "transient_local", "publish_debug": True,
                  "reference_images_dir": str(demo_data / "images"), "qos": "reliable",
                  "relocalize_wait_s": 30.0, "diagnostics_period_s": 0.5}
        with node_and_client(params, log, domain_id()) as (node, client):
            state = {"srv": srv, "node": node, "client": client, "stamp": [time.time_ns()],
                     "pose": client.record(PoseWithCovarianceStamped, "pose"),
                     "debug": client.record(CompressedImage, f"{NODE}/debug_image/compressed"),
                     "candidates": client.record(Candidates, f"{NODE}/candidates")}

            def tick():  # the camera: a fresh frame each call
                state["stamp"][0] += 1
                client.image_pub.publish(image_msg(rgb, state["stamp"][0]))
            state["tick"] = tick
            yield state


def _call_all(client, name: str, futures_or_n, tick, timeout_s: float = 40.0):
    from std_srvs.srv import Trigger

    cli = client.node.create_client(Trigger, name)
    assert cli.wait_for_service(timeout_sec=20.0)
    futs = [cli.call_async(Trigger.Request()) for _ in range(futures_or_n)]
    client.wait_for(lambda: all(f.done() for f in futs), timeout_s, tick=tick, period_s=0.2)
    return futs


def _frame_stamp(message: str) -> int:
    sec, nsec = re.search(r"relocalized frame (\d+)\.(\d{9}):", message).groups()
    return int(sec) * 1_000_000_000 + int(nsec)


def test_concurrent_relocalize_callers_share_one_vlm_call(stack):
    """10 callers during one 3 s VLM call: 10 answers with the same result, none 'busy'."""
    from std_srvs.srv import Trigger

    srv, client, tick, node = stack["srv"], stack["client"], stack["tick"], stack["node"]
    cli = client.node.create_client(Trigger, "relocalize")
    assert cli.wait_for_service(timeout_sec=20.0)
    client.wait_for(lambda: False, 1.0, tick=tick, period_s=0.2)  # frames are flowing
    n_vlm = len(srv.requests)
    first = cli.call_async(Trigger.Request())
    assert client.wait_for(lambda: len(srv.requests) > n_vlm, 20.0, tick=tick, period_s=0.1), \
        node.log()
    t_vlm = time.monotonic()  # the VLM call is running: 9 more callers now
    rest = [cli.call_async(Trigger.Request()) for _ in range(9)]
    sent_during = not first.done() and time.monotonic() - t_vlm < VLM_DELAY_S
    futs = [first, *rest]
    client.wait_for(lambda: all(f.done() for f in futs), 40.0, tick=tick, period_s=0.2)
    answers = [f.result() for f in futs if f.done()]
    assert sent_during and len(answers) == 10, node.log()
    assert all(a.success for a in answers), [a.message for a in answers]
    assert len({a.message for a in answers}) == 1, "\n".join(a.message for a in answers)
    assert "busy" not in answers[0].message
    assert len(srv.requests) == n_vlm + 1  # one VLM call answered all ten
    assert "prior openai:fixture-model" in answers[0].message
    stack["relocalized"] = (_frame_stamp(answers[0].message), time.monotonic())


def test_late_subscriber_gets_the_last_fix_and_its_pose(stack):
    """transient_local: a subscriber joining 5 s after the relocalization gets its fix and
    pose; the pose's covariance is the fix's horizontal covariance."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from sensor_msgs.msg import NavSatFix

    client, node = stack["client"], stack["node"]
    stamp, answered = stack["relocalized"]
    time.sleep(max(0.0, answered + 5.0 - time.monotonic()))
    volatile = client.record(NavSatFix, "fix", 10)
    fixes = client.record(NavSatFix, "fix", _tl_qos())
    poses = client.record(PoseWithCovarianceStamped, "pose", _tl_qos())
    assert client.wait_for(lambda: fixes and poses, 15.0), node.log()
    time.sleep(1.0)
    assert volatile == []  # a volatile subscriber joining late gets nothing
    assert len(fixes) == 1 and len(poses) == 1  # depth 1: the last relocalization only
    fix, pose = fixes[0][0], poses[0][0]
    assert stamp_of(fix) == stamp == stamp_of(pose) and fix.status.status == FIX
    assert haversine_km(fix.latitude, fix.longitude, *TRUTH) < 1.0
    fc, pc = list(fix.position_covariance), list(pose.pose.covariance)
    assert (pc[0], pc[1], pc[6], pc[7]) == (fc[0], fc[1], fc[3], fc[4])
    assert pc[14] == fc[8] and pc[35] == UNKNOWN_ANGLE_VAR and pose.header.frame_id == "utm"
    x, y, z = MetricFrame("utm").project(fix.latitude, fix.longitude, fix.altitude)
    p = pose.pose.pose.position
    assert (p.x, p.y, p.z) == pytest.approx((x, y, z), abs=1e-6)
    q = pose.pose.pose.orientation
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)


def test_runtime_threshold_changes_the_next_fix_and_structural_is_refused(stack):
    from rcl_interfaces.srv import DescribeParameters

    client, tick, node = stack["client"], stack["tick"], stack["node"]
    poses = stack["pose"]

    def relocalize_no_prior(success: bool):
        n_fix, n_pose = len(client.fixes), len(poses)
        [fut] = _call_all(client, "relocalize_no_prior", 1, tick)
        assert fut.done() and fut.result().success is success, node.log()
        assert client.wait_for(lambda: len(client.fixes) > n_fix, 10.0), node.log()
        time.sleep(0.5)  # a pose would follow its fix at once
        return client.fixes[-1][0], len(poses) - n_pose, fut.result().message

    ok = client.set_parameters(NODE, {"fix_max_sigma_m": 0.001})
    assert ok[0].successful, ok[0].reason
    # a no-fix result: no pose, and the service says so (success false, the answer in words)
    fix, new_poses, message = relocalize_no_prior(False)
    assert fix.status.status == NO_FIX and new_poses == 0 and "NO_FIX (sigma" in message
    assert client.set_parameters(NODE, {"fix_max_sigma_m": 1.0e6})[0].successful
    fix, new_poses, message = relocalize_no_prior(True)
    assert fix.status.status == FIX and new_poses == 1 and "STATUS_FIX" in message
    assert "parameters changed at runtime (next query): fix_max_sigma_m" in node.log()

    refused = client.set_parameters(NODE, {"map_dir": "/elsewhere", "prior.model": "x",
                                           "top_p": 0, "fallback_status": "maybe"})
    assert not any(r.successful for r in refused)
    assert "map_reload" in refused[0].reason and "restart" in refused[0].reason
    assert "prior provider" in refused[1].reason
    assert refused[2].reason and "choices: no_fix, fix" in refused[3].reason
    desc = client.call(DescribeParameters, f"{NODE}/describe_parameters",
                       DescribeParameters.Request(names=["fix_max_sigma_m", "map_dir"]))
    assert [d.read_only for d in desc.descriptors] == [False, True]


def test_debug_image_for_every_processed_frame(stack, rgb, demo_data):
    client, tick = stack["client"], stack["tick"]
    debug, candidates = stack["debug"], stack["candidates"]

    def processed():
        return int(client.latest_diag().get("frames_processed", -1))
    for _ in range(3):  # the earlier tests' queries, topped up where a loaded machine shared some
        if processed() >= 3:
            break
        _call_all(client, "relocalize", 1, tick)
    assert client.wait_for(lambda: len(debug) == processed() and debug, 15.0), \
        (len(debug), processed())
    assert len(debug) == processed() >= 3  # one debug image per processed frame
    picture = cv2.imdecode(np.frombuffer(bytes(debug[-1][0].data), np.uint8), cv2.IMREAD_COLOR)
    assert picture is not None and picture.shape[0] == 360 + 48
    # the right half is the chosen reference (the query's own picture here), not a placeholder,
    # with the verified matches drawn across both halves as green lines (BGR here)
    ref = cv2.resize(load_image(demo_data / "images" / QUERY)[:, :, ::-1],
                     (picture.shape[1] // 2, 360), interpolation=cv2.INTER_AREA)
    right = picture[60:360, picture.shape[1] - ref.shape[1]:].astype(int)
    green = (right[..., 1] > right[..., 0] + 60) & (right[..., 1] > right[..., 2] + 60)
    exact = (ref[60:360].astype(int)[..., 1] > ref[60:360].astype(int)[..., 0] + 60)
    assert green.sum() > exact.sum() + 500  # match lines, not the picture's own green
    diff = np.abs(right - ref[60:360].astype(int)).mean(axis=2)
    assert diff[~green].mean() < 12.0
    # ~/candidates: the typed answer (vlm_vpr_interfaces/msg/Candidates) of the same frame
    msg = candidates[-1][0]
    answer = msg.answer
    assert msg.header.stamp == answer.header.stamp == debug[-1][0].header.stamp
    assert answer.reference_id == QUERY and answer.status in (-1, 0) and "verified" in \
        answer.flags and answer.p_correct >= 0.95 and math.isfinite(answer.sigma_m)
    rows = answer.candidates
    assert 1 <= len(rows) <= 20 and rows[0].reference_id == QUERY and rows[0].inliers > 100
    weights = [c.posterior if math.isfinite(c.posterior) else 0.0 for c in rows]
    assert all(0.0 <= w <= 1.0 for w in weights) and math.fsum(weights) <= 1.0 + 1e-6
    # publish_debug off at runtime: the next query publishes no debug image
    assert client.set_parameters(NODE, {"publish_debug": False})[0].successful
    n_debug, n_proc = len(debug), processed()
    [fut] = _call_all(client, "relocalize_no_prior", 1, tick)
    assert fut.result().success and client.wait_for(lambda: processed() > n_proc, 10.0)
    time.sleep(0.5)
    assert len(debug) == n_debug
    # on again at runtime: every frame processed from then on has its picture (issue 29: 6 of 8)
    assert client.set_parameters(NODE, {"publish_debug": True})[0].successful
    n_debug, n_proc = len(debug), processed()
    for _ in range(4):
        [fut] = _call_all(client, "relocalize_no_prior", 1, tick)
        assert fut.result().success
    assert client.wait_for(lambda: processed() >= n_proc + 4 and len(debug) - n_debug ==
                           processed() - n_proc, 15.0), (len(debug) - n_debug,
                                                         processed() - n_proc)


def _layout_topics(layout: dict) -> dict[str, str]:
    """panel id -> the topic it shows (the first topic field each panel kind uses)."""
    out = {}
    for pid, cfg in layout["configById"].items():
        topic = (cfg.get("imageMode", {}).get("imageTopic") or cfg.get("followTopic")
                 or cfg.get("topicToRender") or cfg.get("topicPath"))
        assert topic, f"{pid} shows no topic"
        out[pid] = topic.split(".")[0] if pid.startswith("RawMessages") else topic
    return out


def _panel_ids(tree) -> set[str]:
    if isinstance(tree, str):
        return {tree}
    return _panel_ids(tree["first"]) | _panel_ids(tree["second"])


def test_foxglove_layout_shows_the_nodes_topics(stack):
    """The shipped layout (camera, map with the fix, debug image, diagnostics, candidates)
    names the topics this node really has, with the launch file's default camera remap."""
    import ast
    import json
    from pathlib import Path

    launch = Path(__file__).resolve().parents[1] / "launch_scripts"
    layout = json.loads((launch / "vlm_vpr_foxglove.json").read_text())
    topics = _layout_topics(layout)
    assert _panel_ids(layout["layout"]) == set(topics)  # every configured panel is placed
    client = stack["client"]
    published = {n for n, _ in client.node.get_publisher_names_and_types_by_node(
        "vlm_vpr_node", "/")}
    subscribed = {n for n, _ in client.node.get_subscriber_names_and_types_by_node(
        "vlm_vpr_node", "/")}
    tree = ast.parse((launch / "vlm_vpr.launch.py").read_text())
    default_image = next(n.keywords[0].value.value for n in ast.walk(tree)
                         if isinstance(n, ast.Call) and getattr(n.func, "id", "") ==
                         "DeclareLaunchArgument" and n.args[0].value == "image")
    for pid, topic in topics.items():
        if pid == "Image!vprcamera":  # the camera's compressed stream (the README's replay
            # recipe and image_transport cameras): the node's 'image/compressed' in the launch
            assert topic == default_image + "/compressed" and "/image" in subscribed
        else:
            assert topic in published, f"{pid}: {topic} not among {sorted(published)}"
    assert {"/fix", "/diagnostics", f"{NODE}/debug_image/compressed",
            f"{NODE}/candidates"} <= set(topics.values())
    status = layout["configById"]["DiagnosticStatusPanel!vprstatus"]
    diag = client.diags[-1][0].status[0]
    assert status["selectedName"] == diag.name and status["selectedHardwareId"] == \
        diag.hardware_id
