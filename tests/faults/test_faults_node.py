"""A burst of relocalize calls against a live node whose VLM hangs: every call is answered
(the result, or busy/scheduled within relocalize_wait_s) and pending calls share one query."""

from __future__ import annotations

import time

import pytest

from chat_server import ChatServer
from node_harness import domain_id, image_msg, node_and_client

pytestmark = pytest.mark.timeout(150)
CANARY = "nodecanarypw-31337abc"
N_CALLS = 300
WAIT_S = 4.0


@pytest.mark.fault("node_relocalize_burst")
def test_relocalize_burst_all_answered_one_shared_query(demo_map, demo_data, tmp_path):
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_srvs.srv import Trigger

    from vlm_vpr_ros.files.images import load_image

    rgb = load_image(sorted((demo_data / "images").iterdir())[0])
    with ChatServer("hang") as srv:
        url = srv.base_url.replace("http://", f"http://u:{CANARY}@")
        params = {"map_dir": str(demo_map), "prior_provider": "openai",
                  "prior.base_url": url, "prior.max_retries": 0, "prior.timeout_s": 30.0,
                  "prior_timeout_s": 3.0, "mode": "on_trigger", "relocalize_wait_s": WAIT_S,
                  "diagnostics_period_s": 1.0}
        with node_and_client(params, tmp_path / "node.log", domain_id()) as (node, client):
            trig = client.node.create_client(
                Trigger, "relocalize",
                qos_profile=QoSProfile(depth=N_CALLS + 10,
                                       reliability=ReliabilityPolicy.RELIABLE))
            assert trig.wait_for_service(timeout_sec=20.0), node.log()
            stamp = [time.time_ns()]

            def tick():
                stamp[0] += 1
                client.image_pub.publish(image_msg(rgb, stamp[0]))

            client.wait_for(lambda: False, 1.0, tick=tick, period_s=0.05)
            t0 = time.monotonic()
            futures = [trig.call_async(Trigger.Request()) for _ in range(N_CALLS)]
            sent = time.monotonic() - t0
            done = client.wait_for(lambda: all(f.done() for f in futures), 60.0, tick=tick,
                                   period_s=0.1)
            took = time.monotonic() - t0
            answers = [f.result() for f in futures if f.done() and f.result() is not None]
            n_requests = len(srv.requests)
            log = node.log()
            alive = node.alive()
    assert done and len(answers) == N_CALLS, (
        f"{len(answers)}/{N_CALLS} answered in {took:.0f} s\n{log[-3000:]}")
    assert alive
    busy = sum(a.message.startswith("busy") for a in answers)
    results = sum(a.message.startswith(("relocalized", "relocalization")) for a in answers)
    assert busy + results == N_CALLS, {a.message[:60] for a in answers}
    # the burst (sent within `sent` s) shares the pending query: a handful of VLM requests,
    # never one per call; nobody waited much longer than relocalize_wait_s + a query
    assert 1 <= n_requests <= 1 + int((took + sent) / 3.0) + 1 and n_requests < 10
    assert took < WAIT_S + 3.0 + 20.0
    assert CANARY not in log and "u:***@" not in log.replace("***", "***")
