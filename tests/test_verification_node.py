"""The node on frames that show nothing (lens cap, white-out, grey, noise) over a real ROS 2
graph: every NavSatFix is STATUS_NO_FIX, diagnostics say WARN, and the relocalize answer, the
diagnostics and the published covariance carry the same sigma and status (issue 18)."""

from __future__ import annotations

import math
import re

import pytest

from node_harness import domain_id, image_msg, node_and_client
from test_verification_maps import featureless_frames

pytestmark = pytest.mark.timeout(180)
NO_FIX = -1


@pytest.fixture(scope="module")
def graph(demo_map, tmp_path_factory):
    """on_trigger mode: one query per relocalize call, on the frame just published."""
    params = {"map_dir": str(demo_map), "mode": "on_trigger", "diagnostics_period_s": 0.5,
              "relocalize_wait_s": 30.0, "max_frame_age_s": 30.0}
    log = tmp_path_factory.mktemp("node_v") / "node.log"
    with node_and_client(params, log, domain_id()) as (node, client):
        yield node, client


def test_featureless_frames_are_no_fix_everywhere(graph):
    node, client = graph
    stamp = 1_700_000_000_000_000_000
    for name, frame in featureless_frames().items():
        stamp += 10**9
        n0 = len(client.fixes)
        client.image_pub.publish(image_msg(frame, stamp))
        res = client.call_relocalize(timeout_s=40.0,
                                     tick=lambda: client.image_pub.publish(
                                         image_msg(frame, stamp)))
        assert res is not None, f"{name}: no answer\n" + node.log()
        assert not res.success and "NO_FIX" in res.message, res.message  # nothing to act on
        got = client.wait_for(lambda: len(client.fixes) > n0, 20.0)
        assert got, f"{name}: no NavSatFix\n" + node.log()
        fix, _ = client.fixes[-1]
        assert fix.status.status == NO_FIX, f"{name}: {res.message}"
        sigma = math.sqrt(fix.position_covariance[0])
        # the answer states the status and the published sigma
        assert "NO_FIX" in res.message, res.message
        said = float(re.search(r"sigma (\d+) m", res.message).group(1))
        assert abs(said - sigma) <= 0.5 + 1e-6 * sigma, (said, sigma)
        diag = client.wait_for(lambda: (d := client.latest_diag()) and
                               d.get("status") == "STATUS_NO_FIX" and
                               abs(float(d["last_sigma_m"]) - sigma) < 1e-3 * sigma and d,
                               10.0)
        assert diag and diag["_level"] == "WARN", client.latest_diag()
        assert diag["_message"].startswith("no precise fix: STATUS_NO_FIX")
    assert node.alive()
