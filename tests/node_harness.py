"""TEST/BENCHMARK HARNESS for vlm_vpr_node: run it as a separate process and talk to it over a
real ROS 2 graph (rclpy + Fast DDS, loopback only). Not part of the package.

* :class:`NodeProcess` starts ``sys.executable -m vlm_vpr_ros.ros.node --ros-args -p ...`` with its
  own ``ROS_DOMAIN_ID`` and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, logs to a file, and is
  stopped by its own PID (SIGINT, then SIGKILL after a grace period).
* :class:`GraphClient` owns a fresh rclpy ``Context`` and node, spins it on a background thread,
  publishes images and records ``fix`` / ``/diagnostics`` messages with their arrival time.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

REPO = Path(__file__).resolve().parents[1]
_counter = itertools.count()
#: domain ids reserved for the node tests and benchmark (other suites use lower ids)
DOMAIN_RANGE = (60, 100)


def domain_id() -> int:
    """A domain for one test graph: under pytest-xdist each worker (gw0, gw1, ...) cycles
    through its own slice of :data:`DOMAIN_RANGE`, so two workers never share a graph."""
    lo, hi = DOMAIN_RANGE
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if worker.startswith("gw"):
        count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
        span = (hi - lo + 1) // max(1, count)
        return lo + (int(worker[2:]) % count) * span + next(_counter) % span
    return lo + (os.getpid() * 7 + next(_counter)) % (hi - lo + 1)


def ros_env(domain: int) -> dict[str, str]:
    return {**os.environ, "ROS_DOMAIN_ID": str(domain),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "PYTHONUNBUFFERED": "1"}


def _ros_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return v if v else "''"
    return repr(v)


class NodeProcess:
    """vlm_vpr_node in its own process; use as a context manager."""

    def __init__(self, params: dict[str, Any], log_path: Path, domain: int,
                 extra_args: list[str] | None = None, lifecycle: bool = False,
                 params_file: Path | None = None) -> None:
        self.params, self.log_path, self.domain = params, Path(log_path), domain
        self.params_file = params_file  # given before the -p values (later ones win)
        self.extra_args = extra_args or []
        self.lifecycle = lifecycle
        self.proc: subprocess.Popen | None = None

    def start(self) -> "NodeProcess":
        args = [sys.executable, "-m", "vlm_vpr_ros.ros.node", *(["--lifecycle"] if self.lifecycle
                                                            else []), "--ros-args"]
        if self.params_file is not None:
            args += ["--params-file", str(self.params_file)]
        for k, v in self.params.items():
            args += ["-p", f"{k}:={_ros_value(v)}"]
        self._log = self.log_path.open("w")
        self.proc = subprocess.Popen(args + self.extra_args, stdout=self._log,
                                     stderr=subprocess.STDOUT, env=ros_env(self.domain),
                                     cwd=REPO)
        return self

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def wait_log(self, text: str, timeout_s: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if text in self.log():
                return True
            if not self.alive():
                return text in self.log()
            time.sleep(0.1)
        return False

    def rss_kib(self) -> int:
        """Resident set size of the node process (KiB), from /proc."""
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
        return 0

    def stop(self, grace_s: float = 10.0) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(grace_s)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        self._log.close()
        return self.proc.returncode

    def __enter__(self) -> "NodeProcess":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def image_msg(rgb: np.ndarray, stamp_ns: int, frame_id: str = "camera_test",
              encoding: str = "rgb8") -> Any:
    from sensor_msgs.msg import Image

    h, w = rgb.shape[:2]
    msg = Image(height=h, width=w, encoding=encoding, is_bigendian=0, step=w * 3)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = frame_id
    msg.data = np.ascontiguousarray(rgb).tobytes()
    return msg


def compressed_msg(data: bytes, stamp_ns: int, fmt: str = "jpeg",
                   frame_id: str = "camera_test") -> Any:
    from sensor_msgs.msg import CompressedImage

    msg = CompressedImage(format=fmt, data=bytes(data))
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = frame_id
    return msg


def stamp_of(msg: Any) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


class GraphClient:
    """Publisher/recorder on a fresh rclpy context; use as a context manager."""

    def __init__(self, domain: int, image_qos_depth: int = 10) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from sensor_msgs.msg import CompressedImage, Image, NavSatFix
        from std_srvs.srv import Trigger

        saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
        os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        try:  # the DDS participant reads the environment when the context starts
            self.ctx = rclpy.Context()
            rclpy.init(context=self.ctx, domain_id=domain)
            self.node = Node(f"vlm_vpr_test_{os.getpid()}", context=self.ctx)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        self.lock = threading.Lock()
        self.fixes: list[tuple[Any, int]] = []  # (msg, arrival time.time_ns())
        self.diags: list[tuple[Any, int]] = []
        self.image_pub = self.node.create_publisher(Image, "image", image_qos_depth)
        self.compressed_pub = self.node.create_publisher(CompressedImage, "image/compressed",
                                                         image_qos_depth)
        self.node.create_subscription(NavSatFix, "fix", self._record(self.fixes), 50)
        self.node.create_subscription(DiagnosticArray, "/diagnostics",
                                      self._record(self.diags), 50)
        self.trigger = self.node.create_client(Trigger, "relocalize")
        self._trigger_type = Trigger
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def _record(self, store: list) -> Callable[[Any], None]:
        def cb(msg: Any) -> None:
            with self.lock:
                store.append((msg, time.time_ns()))
        return cb

    def wait_for(self, pred: Callable[[], Any], timeout_s: float,
                 tick: Callable[[], None] | None = None, period_s: float = 0.05) -> Any:
        """Poll ``pred`` (calling ``tick``, e.g. a publish, each period) until truthy."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if tick is not None:
                tick()
            with self.lock:
                value = pred()
            if value:
                return value
            time.sleep(period_s)
        return None

    def wait_subscribed(self, timeout_s: float = 20.0, compressed: bool = False) -> bool:
        pub = self.compressed_pub if compressed else self.image_pub
        return bool(self.wait_for(lambda: pub.get_subscription_count() > 0, timeout_s))

    def latest_diag(self) -> dict[str, str]:
        from msg_adapters.diagnostics import level_name

        if not self.diags:
            return {}
        st = self.diags[-1][0].status[0]
        return {"_level": level_name(st.level), "_message": st.message,
                **{kv.key: kv.value for kv in st.values}}

    def call(self, srv_type: Any, name: str, request: Any, timeout_s: float = 20.0) -> Any:
        """Call any service (waiting for it first); None when there is no answer in time."""
        client = self.node.create_client(srv_type, name)
        try:
            if not client.wait_for_service(timeout_sec=timeout_s):
                return None
            fut = client.call_async(request)
            self.wait_for(fut.done, timeout_s)
            return fut.result() if fut.done() else None
        finally:
            self.node.destroy_client(client)

    def record(self, msg_type: Any, topic: str, qos: Any = 10) -> list:
        """Subscribe to ``topic`` now; the returned list fills with (msg, arrival ns)."""
        store: list = []
        self.node.create_subscription(msg_type, topic, self._record(store), qos)
        return store

    def set_parameters(self, node_name: str, values: dict[str, Any],
                       timeout_s: float = 20.0) -> list:
        """``set_parameters`` on another node: one SetParametersResult per value."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        req = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg()
                                                for k, v in values.items()])
        resp = self.call(SetParameters, f"{node_name}/set_parameters", req, timeout_s)
        assert resp is not None, f"{node_name}/set_parameters did not answer"
        return list(resp.results)

    def call_relocalize(self, timeout_s: float = 30.0,
                        tick: Callable[[], None] | None = None) -> Any:
        if not self.trigger.wait_for_service(timeout_sec=20.0):
            return None
        fut = self.trigger.call_async(self._trigger_type.Request())
        self.wait_for(fut.done, timeout_s, tick=tick)
        return fut.result() if fut.done() else None

    def close(self) -> None:
        import rclpy

        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)
        self._thread.join(5.0)

    def __enter__(self) -> "GraphClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextlib.contextmanager
def node_and_client(params: dict[str, Any], log_path: Path, domain: int,
                    compressed: bool = False) -> Iterator[tuple[NodeProcess, GraphClient]]:
    """Start the node, connect a :class:`GraphClient` and wait until the node subscribes to
    ``image`` (and ``image/compressed`` when asked); both are always stopped on exit."""
    node = NodeProcess(params, log_path, domain).start()
    client = None
    try:
        client = GraphClient(domain)
        assert client.wait_subscribed(30.0), "node did not subscribe:\n" + node.log()
        if compressed:
            assert client.wait_subscribed(10.0, compressed=True), node.log()
        yield node, client
    finally:
        if client is not None:
            client.close()
        node.stop()
