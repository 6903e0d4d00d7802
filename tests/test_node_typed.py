"""The typed relocalization interfaces over a real ROS 2 graph (node = a separate process):
the ``relocalize_typed`` service against the published NavSatFix, the ``relocalize`` action's
feedback, cancel and timeout (an abandoned answer publishes no pose), and late joiners on
``transient_local`` (never a pose older than the latest fix). ROS_DOMAIN_IDs 150-159."""

from __future__ import annotations

import hashlib
import math
import time

import numpy as np
import pytest

from node_harness import NodeProcess, GraphClient, compressed_msg, stamp_of

pytest.importorskip("vlm_vpr_interfaces", reason="vlm_vpr_interfaces not built (make setup)")
pytestmark = pytest.mark.timeout(240)
QUERY = "546314506564628.jpg"  # Sanluri, Sardinia (test_node_ros.py)
TRUTH = (39.55910238557, 8.8888751944543)


@pytest.fixture(scope="module")
def rgb(demo_data):
    from vlm_vpr_ros.files.images import load_image

    return load_image(demo_data / "images" / QUERY)


class _Run:
    """A node process and a client on one domain; frames published on demand, as lossless PNG
    ``CompressedImage`` messages: best-effort delivery as a camera's (the "next frame" rules
    need it), without the loss of UDP fragments of 0.9 MB raw frames on a loaded machine, which
    once lost every frame for 60 s in CI (raw-frame loss is measured by bench_qos.py)."""

    def __init__(self, params, log, domain):
        params = {"subscribe_raw": False, "subscribe_compressed": True, **params}
        self.node = NodeProcess(params, log, domain).start()
        self.client = GraphClient(domain)
        self.stamp = time.time_ns()
        self._png: dict[bytes, bytes] = {}
        assert self.client.wait_subscribed(60.0, compressed=True), \
            "node did not subscribe:\n" + self.node.log()

    def frame(self, rgb) -> int:
        import cv2

        self.stamp += 1_000_000
        key = hashlib.sha256(np.ascontiguousarray(rgb).data).digest()
        if key not in self._png:
            ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
            assert ok
            self._png[key] = buf.tobytes()
        self.client.compressed_pub.publish(compressed_msg(self._png[key], self.stamp, fmt="png"))
        return self.stamp

    def close(self):
        self.client.close()
        self.node.stop()


def _params(demo_map, **extra):
    return {"map_dir": str(demo_map), "prior_provider": "fixed",
            "prior.lat": TRUTH[0] + 0.02, "prior.lon": TRUTH[1] - 0.02,
            "mode": "on_trigger", "diagnostics_period_s": 1.0, **extra}


def _send_goal(client, goal, feedback):
    from rclpy.action import ActionClient
    from vlm_vpr_interfaces.action import Relocalize

    ac = ActionClient(client.node, Relocalize, "relocalize")
    assert ac.wait_for_server(timeout_sec=30.0)
    fut = ac.send_goal_async(goal, feedback_callback=lambda fb: feedback.append(fb.feedback))
    assert client.wait_for(fut.done, 30.0)
    return ac, fut.result()


def test_typed_service_equals_the_published_fix(demo_map, rgb, tmp_path):
    from sensor_msgs.msg import NavSatFix
    from vlm_vpr_interfaces.msg import Answer
    from vlm_vpr_interfaces.srv import Relocalize

    run = _Run(_params(demo_map), tmp_path / "node.log", 150)
    try:
        fixes = run.client.record(NavSatFix, "fix")
        sent = [run.frame(rgb)]
        req = Relocalize.Request(next_frame=False, no_prior=False, timeout_s=60.0)
        client = run.client.node.create_client(Relocalize, "relocalize_typed")
        assert client.wait_for_service(timeout_sec=30.0)
        fut = client.call_async(req)
        run.client.wait_for(fut.done, 90.0, tick=lambda: sent.append(run.frame(rgb)),
                            period_s=0.5)
        assert fut.done(), run.node.log()
        ans = fut.result().answer
        assert ans.outcome == Answer.OUTCOME_ANSWERED and ans.success, ans.message
        assert run.client.wait_for(lambda: any(stamp_of(m) == stamp_of(ans) for m, _ in fixes),
                                   10.0)
        fix = next(m for m, _ in fixes if stamp_of(m) == stamp_of(ans))
        assert stamp_of(ans) in sent
        assert (ans.latitude, ans.longitude, ans.altitude) == (fix.latitude, fix.longitude,
                                                               fix.altitude)
        assert ans.status == fix.status.status == Answer.STATUS_FIX
        assert ans.sigma_m == pytest.approx(math.sqrt(fix.position_covariance[0]), rel=1e-12)
        assert ans.header.frame_id == fix.header.frame_id
        assert 0.95 <= ans.p_correct <= 1.0 and ans.reference_id and len(ans.candidates) >= 1
        assert ans.candidates[0].reference_id == ans.reference_id
        assert ans.prior_source == "fixed" and ans.reason == ""
        # bad timeout: rejected with the reason, nothing scheduled
        fut = client.call_async(Relocalize.Request(timeout_s=-1.0))
        run.client.wait_for(fut.done, 20.0)
        bad = fut.result().answer
        assert bad.outcome == Answer.OUTCOME_REJECTED and "timeout_s" in bad.reason
    finally:
        run.close()


def test_action_feedback_cancel_and_timeout_publish_no_pose(demo_map, rgb, tmp_path):
    from action_msgs.msg import GoalStatus
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from sensor_msgs.msg import NavSatFix
    from vlm_vpr_interfaces.action import Relocalize
    from vlm_vpr_interfaces.msg import Answer

    run = _Run(_params(demo_map, max_frame_age_s=0.5), tmp_path / "node.log", 151)
    try:
        poses = run.client.record(PoseWithCovarianceStamped, "pose")
        fixes = run.client.record(NavSatFix, "fix")
        # 1. a goal answered: every stage reported, in order
        feedback: list = []
        run.frame(rgb)
        ac, handle = _send_goal(run.client, Relocalize.Goal(timeout_s=90.0), feedback)
        assert handle.accepted
        res = handle.get_result_async()
        run.client.wait_for(res.done, 120.0, tick=lambda: run.frame(rgb), period_s=0.5)
        assert res.done(), run.node.log()
        answer = res.result().result.answer
        assert res.result().status == GoalStatus.STATUS_SUCCEEDED and answer.success
        stages = [f.stage_name for f in feedback]
        assert len(set(stages)) >= 3 and stages[-2:] == ["retrieving", "verifying"], stages
        assert [f.stage for f in feedback] == sorted(f.stage for f in feedback)
        assert run.client.wait_for(lambda: len(poses) == 1, 10.0)
        # 2. cancelled while waiting for a frame (none comes): cancelled cleanly, and the
        # frames that come afterwards publish no pose and no fix (on_trigger)
        time.sleep(1.0)  # older than max_frame_age_s: the goal waits for the next frame
        n_fix = len(fixes)
        feedback = []
        ac, handle = _send_goal(run.client, Relocalize.Goal(timeout_s=60.0), feedback)
        time.sleep(1.0)
        cancel = handle.cancel_goal_async()
        assert run.client.wait_for(cancel.done, 20.0)
        res = handle.get_result_async()
        assert run.client.wait_for(res.done, 20.0)
        assert res.result().status == GoalStatus.STATUS_CANCELED
        assert res.result().result.answer.outcome == Answer.OUTCOME_CANCELLED
        # 3. timed out (no frame within 1 s)
        ac, handle = _send_goal(run.client, Relocalize.Goal(timeout_s=1.0), [])
        res = handle.get_result_async()
        assert run.client.wait_for(res.done, 20.0)
        assert res.result().status == GoalStatus.STATUS_ABORTED
        assert res.result().result.answer.outcome == Answer.OUTCOME_NO_FRAME
        for _ in range(10):  # frames arrive late: nobody waits any more
            run.frame(rgb)
            time.sleep(0.5)
        time.sleep(3.0)
        assert len(poses) == 1 and len(fixes) == n_fix, run.node.log()
        # 4. bad goals are rejected
        for bad in (0.0, -1.0, math.nan):
            ac, handle = _send_goal(run.client, Relocalize.Goal(timeout_s=bad), [])
            assert not handle.accepted
        assert "goal rejected: timeout_s must be a positive finite number" in run.node.log()
    finally:
        run.close()


def test_trigger_wait_zero_is_never_success(demo_map, rgb, tmp_path):
    from std_srvs.srv import Trigger

    run = _Run(_params(demo_map, relocalize_wait_s=0.0), tmp_path / "node.log", 152)
    try:
        resp = run.client.call(Trigger, "relocalize", Trigger.Request())
        assert resp is not None and not resp.success and "scheduled" in resp.message
    finally:
        run.close()


def test_late_joiner_gets_no_pose_older_than_the_latest_fix(demo_map, rgb, tmp_path):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import NavSatFix
    from std_srvs.srv import Trigger

    params = _params(demo_map, fix_durability="transient_local", relocalize_wait_s=60.0)
    run = _Run(params, tmp_path / "node.log", 153)
    try:
        live = run.client.record(NavSatFix, "fix")
        client = run.client.node.create_client(Trigger, "relocalize")
        assert client.wait_for_service(timeout_sec=30.0)
        run.frame(rgb)
        fut = client.call_async(Trigger.Request())
        run.client.wait_for(fut.done, 90.0, tick=lambda: run.frame(rgb), period_s=0.5)
        assert fut.done() and fut.result().success, run.node.log()
        # then a NO_FIX: a black frame (featureless: never a fix)
        black = np.zeros_like(rgb)
        n = len(live)
        nxt = run.client.node.create_client(Trigger, "relocalize_next_frame")
        assert nxt.wait_for_service(timeout_sec=30.0)
        fut = nxt.call_async(Trigger.Request())
        run.client.wait_for(fut.done, 90.0, tick=lambda: run.frame(black), period_s=0.5)
        assert fut.done() and not fut.result().success
        assert run.client.wait_for(lambda: len(live) > n and live[-1][0].status.status == -1,
                                   10.0)
        latest = stamp_of(live[-1][0])
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
        late_fix = run.client.record(NavSatFix, "fix", qos)
        late_pose = run.client.record(PoseWithCovarianceStamped, "pose", qos)
        assert run.client.wait_for(lambda: late_fix, 10.0)
        time.sleep(2.0)
        assert stamp_of(late_fix[-1][0]) == latest and late_fix[-1][0].status.status == -1
        assert all(stamp_of(p) >= latest for p, _ in late_pose), "stale pose for a late joiner"
    finally:
        run.close()
