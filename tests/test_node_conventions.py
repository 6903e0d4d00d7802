"""ROS 2 conventions of vlm_vpr_node over a real graph (rclpy + Fast DDS, separate process):
parameter descriptors read back with describe_parameters, read-only refusal, QoS defaults and
qos_overrides, the lifecycle variant through its services, and start-up type errors."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from node_harness import GraphClient, NodeProcess, domain_id, image_msg, ros_env
from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.runtime.params import PARAMETER_SPECS

pytestmark = pytest.mark.timeout(120)
REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / "launch_scripts" / "vlm_vpr_params.yaml"
QUERY = "546314506564628.jpg"
# rcl_interfaces ParameterType values
BOOL, INT, DOUBLE, STRING = 1, 2, 3, 4
KINDS = {"bool": BOOL, "int": INT, "float": DOUBLE, "str": STRING}


@pytest.fixture(scope="module")
def rgb(demo_data):
    return load_image(demo_data / "images" / QUERY)


def _wait_node_service(client: GraphClient, name: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if any(n == name for n, _ in client.node.get_service_names_and_types()):
            return
        time.sleep(0.1)
    raise AssertionError(f"service {name} never appeared")


def test_parameters_are_described_read_only_and_qos_is_best_effort(demo_map, tmp_path, rgb):
    """Params file + -p (an int given for a float): every parameter comes back through
    describe_parameters with its description, type, range and read_only (structural ones) or
    writable (runtime tuning); a structural change is refused with how to make it; the default
    image QoS is best effort, so a BEST_EFFORT camera gives fixes."""
    from rcl_interfaces.msg import Parameter, ParameterValue
    from rcl_interfaces.srv import DescribeParameters, GetParameters, SetParameters
    from rclpy.qos import qos_profile_sensor_data

    dom = domain_id()
    node = NodeProcess({"map_dir": str(demo_map), "min_period_s": 2, "prior_provider": "fixed",
                        "prior.lat": 39.58, "prior.lon": 8.87}, tmp_path / "node.log", dom,
                       params_file=PARAMS).start()
    try:
        with GraphClient(dom) as client:
            names = [*PARAMETER_SPECS, "prior.lat"]
            _wait_node_service(client, "/vlm_vpr_node/describe_parameters")
            desc = client.call(DescribeParameters, "/vlm_vpr_node/describe_parameters",
                               DescribeParameters.Request(names=names))
            assert desc is not None, node.log()
            by_name = {d.name: d for d in desc.descriptors}
            for name, spec in PARAMETER_SPECS.items():
                d = by_name[name]
                assert d.description == spec.doc and d.type == KINDS[spec.kind], name
                assert d.read_only == spec.read_only, name
                if spec.range is not None:
                    rng = d.integer_range if spec.kind == "int" else d.floating_point_range
                    assert len(rng) == 1 and (rng[0].from_value, rng[0].to_value) == \
                        pytest.approx(spec.range), name
                if spec.choices:
                    assert all(c in d.additional_constraints for c in spec.choices)
            assert by_name["qos_depth"].integer_range[0].to_value == 10
            assert by_name["prior.lat"].read_only and by_name["prior.lat"].description
            got = client.call(GetParameters, "/vlm_vpr_node/get_parameters",
                              GetParameters.Request(names=["min_period_s", "qos", "map_dir"]))
            assert got.values[0].type == DOUBLE and got.values[1].string_value == "sensor_data"
            assert got.values[2].string_value == str(demo_map)
            assert not by_name["top_p"].read_only and by_name["qos"].read_only
            refused = client.call(SetParameters, "/vlm_vpr_node/set_parameters",
                                  SetParameters.Request(parameters=[Parameter(
                                      name="qos_depth",
                                      value=ParameterValue(type=INT, integer_value=7))]))
            assert not refused.results[0].successful
            assert "cannot change at runtime" in refused.results[0].reason
            assert "restart the node" in refused.results[0].reason
            qos = client.call(GetParameters, "/vlm_vpr_node/get_parameters", GetParameters.Request(
                names=["qos_overrides./image.subscription.reliability"]))
            assert qos.values[0].string_value == "best_effort"
            # a BEST_EFFORT (sensor-data) camera publisher is matched and localized
            from sensor_msgs.msg import Image

            be_pub = client.node.create_publisher(Image, "image", qos_profile_sensor_data)
            assert client.wait_for(lambda: be_pub.get_subscription_count() > 0, 20.0)
            t = [time.time_ns()]

            def tick():
                t[0] += 1
                be_pub.publish(image_msg(rgb, t[0]))
            assert client.wait_for(lambda: client.fixes, 30.0, tick=tick, period_s=0.1), \
                node.log()
    finally:
        node.stop()


def test_qos_overrides_are_honoured(demo_map, tmp_path):
    """qos_overrides./image.subscription.reliability:=reliable makes the subscription reliable:
    a best-effort publisher no longer matches, a reliable one does."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    dom = domain_id()
    with NodeProcess({"map_dir": str(demo_map),
                      "qos_overrides./image.subscription.reliability": "reliable"},
                     tmp_path / "node.log", dom) as node, GraphClient(dom) as client:
        rel = client.node.create_publisher(Image, "image", QoSProfile(
            depth=5, reliability=ReliabilityPolicy.RELIABLE))
        be = client.node.create_publisher(Image, "image", QoSProfile(
            depth=5, reliability=ReliabilityPolicy.BEST_EFFORT))
        assert client.wait_for(lambda: rel.get_subscription_count() > 0, 30.0), node.log()
        time.sleep(1.0)
        assert be.get_subscription_count() == 0
        assert "(sensor_data: reliable, depth 5)" in node.log()


def test_lifecycle_node_through_its_services(demo_map, tmp_path, rgb):
    """configure loads the map (no intake yet), activate subscribes and publishes, deactivate
    stops both without reloading the map, cleanup frees it; all through change_state."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState
    from std_srvs.srv import Trigger

    dom = domain_id()
    # reliable like the publisher: this tests the transitions, not the UDP fragment loss of
    # full-size raw frames over best effort on a loaded machine (benchmarks/bench_qos.py)
    params = {"map_dir": str(demo_map), "min_period_s": 0.2, "diagnostics_period_s": 0.5,
              "qos": "reliable"}
    with NodeProcess(params, tmp_path / "node.log", dom, lifecycle=True) as node, \
            GraphClient(dom) as client:
        def state() -> str:
            r = client.call(GetState, "/vlm_vpr_node/get_state", GetState.Request())
            return r.current_state.label if r is not None else "no answer"

        def change(tid: int) -> bool:
            r = client.call(ChangeState, "/vlm_vpr_node/change_state",
                            ChangeState.Request(transition=Transition(id=tid)), 30.0)
            return bool(r and r.success)

        stamps = [time.time_ns()]

        def tick():
            stamps[0] += 1
            client.image_pub.publish(image_msg(rgb, stamps[0]))

        _wait_node_service(client, "/vlm_vpr_node/get_state")
        assert state() == "unconfigured"
        assert change(Transition.TRANSITION_CONFIGURE), node.log()
        assert state() == "inactive" and "map loaded" in node.log()
        time.sleep(1.0)
        assert client.image_pub.get_subscription_count() == 0  # no intake while inactive
        inactive = client.call(Trigger, "relocalize", Trigger.Request())
        assert not inactive.success and "not active" in inactive.message
        reloaded = client.call(Trigger, "map_reload", Trigger.Request())  # for the activate
        assert reloaded.success and "71 references (used from the next activate)" in \
            reloaded.message, reloaded.message

        assert change(Transition.TRANSITION_ACTIVATE) and state() == "active"
        assert client.wait_subscribed(20.0), node.log()
        assert client.wait_for(lambda: client.fixes, 30.0, tick=tick, period_s=0.1), node.log()

        assert change(Transition.TRANSITION_DEACTIVATE) and state() == "inactive"
        assert client.wait_for(lambda: client.image_pub.get_subscription_count() == 0, 10.0)
        with client.lock:
            n_fix, n_diag = len(client.fixes), len(client.diags)
        client.wait_for(lambda: False, 1.5, tick=tick, period_s=0.1)
        assert len(client.fixes) == n_fix and len(client.diags) == n_diag  # silent

        assert change(Transition.TRANSITION_ACTIVATE), node.log()
        assert client.wait_subscribed(20.0), node.log()  # the new subscription is matched
        assert client.wait_for(lambda: len(client.fixes) > n_fix, 30.0, tick=tick,
                               period_s=0.1), node.log()
        assert node.log().count("map loaded") == 1  # deactivate kept the map

        assert change(Transition.TRANSITION_DEACTIVATE)
        assert change(Transition.TRANSITION_CLEANUP) and state() == "unconfigured"
        assert "map and prior provider released" in node.log()
        assert change(Transition.TRANSITION_CONFIGURE) and state() == "inactive"
        assert node.log().count("map loaded") == 2  # configure after cleanup loads it again
        assert node.alive()
    assert node.proc.returncode == 0, node.log()


@pytest.mark.parametrize("how", ["run_node.sh", "lifecycle", "console script"])
def test_wrong_type_next_to_a_params_file_stops_start_up(demo_map, how):
    """rcl silently keeps a params file's top_p: 50 when -p top_p:=abc follows it; every
    launch path still exits 2 with one FATAL line naming the parameter."""
    env = ros_env(domain_id())
    bad = ["-p", f"map_dir:={demo_map}", "-p", "top_p:=abc"]
    if how == "run_node.sh":
        cmd = [str(REPO / "launch_scripts" / "run_node.sh"), *bad]
    elif how == "lifecycle":
        cmd = [sys.executable, "-m", "vlm_vpr_ros.ros.node", "--lifecycle", "--ros-args",
               "--params-file", str(PARAMS), *bad]
    else:
        exe = Path(sys.executable).with_name("vlm_vpr_node")
        if not exe.exists():
            pytest.skip("console script not installed")
        cmd = [str(exe), "--ros-args", "--params-file", str(PARAMS), *bad]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, env=env, cwd=REPO)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out
    fatal = [line for line in out.splitlines() if "FATAL" in line]
    assert len(fatal) == 1 and "'top_p' must be an int, got 'abc'" in fatal[0], out
    assert "Traceback" not in out


def test_unreadable_params_file_is_one_fatal_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    top_p: [1, 2\n")
    proc = subprocess.run([sys.executable, "-m", "vlm_vpr_ros.ros.node", "--ros-args",
                           "--params-file", str(bad)], capture_output=True, text=True,
                          timeout=60, env=ros_env(domain_id()), cwd=REPO)
    assert proc.returncode == 2 and "invalid YAML" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
    assert os.path.basename(str(bad)) in proc.stderr


def test_min_period_runs_on_sim_time(demo_map, tmp_path, rgb):
    """use_sim_time: min_period_s counts /clock seconds. With min_period_s 20 and /clock running
    20x faster than wall time, fixes come about once per wall second (on wall time there would
    be one per 20 s)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock

    dom = domain_id()
    params = {"map_dir": str(demo_map), "use_sim_time": True, "min_period_s": 20.0,
              "qos": "reliable"}
    with NodeProcess(params, tmp_path / "node.log", dom) as node, GraphClient(dom) as client:
        clock_pub = client.node.create_publisher(Clock, "/clock", QoSProfile(
            depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        assert client.wait_subscribed(30.0), node.log()
        sim = {"t": 1_000 * 10**9, "wall": time.monotonic()}

        def tick():
            now = time.monotonic()
            sim["t"] += int((now - sim["wall"]) * 20 * 1e9)  # 20x real time
            sim["wall"] = now
            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = divmod(sim["t"], 10**9)
            clock_pub.publish(msg)
            client.image_pub.publish(image_msg(rgb, sim["t"]))
        client.wait_for(lambda: client.fixes, 20.0, tick=tick, period_s=0.05)
        assert client.fixes, node.log()
        t0, n0 = time.monotonic(), len(client.fixes)
        client.wait_for(lambda: len(client.fixes) >= n0 + 3, 8.0, tick=tick, period_s=0.05)
        took = time.monotonic() - t0
        assert len(client.fixes) >= n0 + 3, f"{len(client.fixes) - n0} fixes in {took:.1f} s"
        # (the very first query may start at time 0, before the first /clock arrives)
        stamps = [m.header.stamp.sec for m, _ in client.fixes[n0:]]
        gaps = [b - a for a, b in zip(stamps, stamps[1:])]
        assert min(gaps) >= 19, gaps  # never closer than min_period_s on the sim clock


def test_lifecycle_configure_fails_cleanly_on_a_bad_map(tmp_path, demo_map, rgb):
    """map_dir missing, then a folder without a valid map: configure fails each time (the node
    stays unconfigured, says why, answers its lifecycle services) as a lifecycle manager
    expects; once the map is there configure -> activate works; shutdown ends the process."""
    import shutil

    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    target = tmp_path / "maps" / "site"  # does not exist yet
    dom = domain_id()
    with NodeProcess({"map_dir": str(target), "min_period_s": 0.2}, tmp_path / "node.log", dom,
                     lifecycle=True) as node, GraphClient(dom) as client:
        def change(tid: int) -> bool:
            r = client.call(ChangeState, "/vlm_vpr_node/change_state",
                            ChangeState.Request(transition=Transition(id=tid)), 30.0)
            assert r is not None, node.log()
            return r.success

        def state() -> str:
            return client.call(GetState, "/vlm_vpr_node/get_state",
                               GetState.Request()).current_state.label

        _wait_node_service(client, "/vlm_vpr_node/change_state")
        assert not change(Transition.TRANSITION_CONFIGURE) and state() == "unconfigured"
        assert "does not exist or is not a folder" in node.log()
        target.mkdir(parents=True)  # a folder without a map
        assert not change(Transition.TRANSITION_CONFIGURE) and state() == "unconfigured"
        assert node.log().count("configure failed") == 2 and "Traceback" not in node.log()
        target.rmdir()
        shutil.copytree(demo_map, target)  # the map arrives (e.g. synced after boot)
        assert change(Transition.TRANSITION_CONFIGURE) and state() == "inactive"
        assert change(Transition.TRANSITION_ACTIVATE) and state() == "active"
        assert client.wait_subscribed(20.0), node.log()
        stamp = [time.time_ns()]

        def tick():
            stamp[0] += 1
            client.image_pub.publish(image_msg(rgb, stamp[0]))
        assert client.wait_for(lambda: client.fixes, 30.0, tick=tick, period_s=0.1), node.log()
        assert change(Transition.TRANSITION_ACTIVE_SHUTDOWN)  # answered, then the process ends
        node.proc.wait(20.0)
    assert node.proc.returncode == 0 and "shut down: the process ends" in node.log()
