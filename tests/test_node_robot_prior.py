"""``prior_topic`` over a real ROS 2 graph (node = a separate process): the robot's NavSatFix is
the prior of a relocalization (its sigma from the covariance), bad messages (NaN / zero /
negative covariance, stamps in the future or far past) are ignored with one WARN per kind and
never become a prior; ``--help`` prints the parameters. ROS_DOMAIN_ID 154."""

from __future__ import annotations

import math
import subprocess
import sys
import time

import pytest

from node_harness import REPO, GraphClient, NodeProcess, image_msg, ros_env

pytest.importorskip("vlm_vpr_interfaces", reason="vlm_vpr_interfaces not built (make setup)")
pytestmark = pytest.mark.timeout(240)
QUERY = "546314506564628.jpg"  # Sanluri, Sardinia (test_node_ros.py)
TRUTH = (39.55910238557, 8.8888751944543)


def _navsat(lat, lon, var, stamp_ns):
    from sensor_msgs.msg import NavSatFix

    m = NavSatFix(latitude=lat, longitude=lon, altitude=0.0)
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    m.header.frame_id = "gps"
    m.status.status = 0
    m.position_covariance = [var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, 100.0]
    m.position_covariance_type = 2
    return m


def _relocalize(client, frame):
    from vlm_vpr_interfaces.srv import Relocalize

    srv = client.node.create_client(Relocalize, "relocalize_typed")
    assert srv.wait_for_service(timeout_sec=30.0)
    fut = srv.call_async(Relocalize.Request(timeout_s=90.0))
    client.wait_for(fut.done, 120.0, tick=frame, period_s=0.5)
    assert fut.done()
    return fut.result().answer


def test_robot_navsat_is_the_prior_and_bad_messages_are_ignored(demo_map, demo_data, tmp_path):
    from sensor_msgs.msg import NavSatFix

    from vlm_vpr_ros.files.images import load_image

    rgb = load_image(demo_data / "images" / QUERY)
    params = {"map_dir": str(demo_map), "prior_provider": "none", "mode": "on_trigger",
              "qos": "reliable", "prior_topic": "gps/fix", "prior_topic_type": "navsat",
              "prior_topic_growth_m_per_s": 2.0, "prior_topic_max_age_s": 60.0,
              "trust_operator_prior": True}
    node = NodeProcess(params, tmp_path / "node.log", 154).start()
    client = GraphClient(154)
    try:
        assert client.wait_subscribed(60.0), node.log()
        gps = client.node.create_publisher(NavSatFix, "gps/fix", 10)
        assert client.wait_for(lambda: gps.get_subscription_count() > 0, 30.0)
        stamp = [time.time_ns()]

        def frame():
            stamp[0] += 1_000_000
            client.image_pub.publish(image_msg(rgb, stamp[0]))

        now = time.time_ns()
        bad = [_navsat(TRUTH[0], TRUTH[1], math.nan, now),
               _navsat(TRUTH[0], TRUTH[1], 0.0, now),
               _navsat(TRUTH[0], TRUTH[1], -25.0, now),
               _navsat(TRUTH[0], TRUTH[1], 100.0, now + 3600 * 10**9),  # an hour ahead
               _navsat(TRUTH[0], TRUTH[1], 100.0, now - 3600 * 10**9)]  # an hour old
        time.sleep(2.0)  # the node's reader matched too (discovery is not symmetric)
        for _ in range(3):
            for m in bad:
                gps.publish(m)
                time.sleep(0.05)
        time.sleep(2.0)
        ans = _relocalize(client, frame)  # only bad estimates so far: no prior at all
        assert ans.prior_source == "" and ("no_prior" in ans.flags or "prior_failed" in ans.flags)
        log = node.log()
        assert log.count("ignoring a message") + log.count("ignoring an estimate") == 4, log
        assert "not positive definite" in log and "in the future" in log and "old" in log
        assert "not finite" in log
        # a good estimate ~1 km off with sigma 30 m: the prior, its sigma grown with age
        good = _navsat(TRUTH[0] + 0.009, TRUTH[1], 900.0, time.time_ns() - 5 * 10**9)
        for _ in range(3):
            gps.publish(good)
            time.sleep(0.3)
        ans = _relocalize(client, frame)
        assert ans.prior_source == "topic:navsat /gps/fix", ans.message
        assert "prior topic:navsat" in ans.message
    finally:
        client.close()
        node.stop()


@pytest.mark.parametrize("cmd", [[sys.executable, "-m", "vlm_vpr_ros.ros.node", "--help"],
                                 [str(REPO / "launch_scripts" / "run_node.sh"), "--help"]])
def test_help_lists_the_parameters_and_exits_0(cmd):
    from vlm_vpr_ros.runtime.params import PARAMETER_SPECS

    res = subprocess.run(cmd, capture_output=True, text=True, timeout=60, env=ros_env(155),
                         cwd=REPO)
    assert res.returncode == 0, res.stderr
    for name, spec in PARAMETER_SPECS.items():
        assert f" {name} ({spec.kind}, default " in res.stdout
    assert "Traceback" not in res.stdout + res.stderr
