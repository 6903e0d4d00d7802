"""``vlm_vpr_node`` / ``vlm_vpr_lifecycle_node``: Image in, NavSatFix + diagnostics out.

ROS 2 wiring only. The query logic lives in :mod:`vlm_vpr_ros.runtime.worker` (pure), message
conversions in :mod:`msg_adapters`, the parameter schema in :mod:`vlm_vpr_ros.runtime.params`.
Both executables share :class:`_Wiring`, in four steps that are the lifecycle transitions:

* parameters (constructor): every parameter declared once with its descriptor (type,
  description, range, read-only); bad values stop start-up with one FATAL line, exit code 2
  (the lifecycle node checks that ``map_dir`` holds a map at configure, which then fails);
* ``load`` (configure): map, prior provider, publishers, relocalize and map_reload services,
  diagnostics timer;
* ``start`` (activate): image subscriptions and the query worker;
* ``stop`` (deactivate): subscriptions and worker gone, map kept; ``unload`` (cleanup) frees it;
* ``shutdown``: as cleanup, then the process ends (exit code 0).

Every caller in progress (relocalize services, action goals) gets its answer before the
services and the action server are destroyed: cleanup and shutdown answer them NOT_ACTIVE and
wait for them (ros/requests.py); on SIGINT / SIGTERM the node does the same while the executor
still spins (rclpy's own signal handler is off: it would invalidate the context first, and a
goal could then no longer be ended).

The plain node runs load + start in its constructor. Callback groups: images and the
diagnostics timer each have their own mutually exclusive group, the relocalize services and
action one reentrant group, map_reload its own reentrant one (one reload at a time, others
answered at once), under a MultiThreadedExecutor with a thread for each relocalize
caller that may wait (``MAX_WAITERS``) on top of the four the other callbacks need; queries run
on the runtime's worker thread, so a slow VLM never delays image intake and waiting callers
never block the executor.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
import time
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future

from vlm_vpr_ros.errors import ConfigError, VlmVprError
from vlm_vpr_ros.runtime.params import NESTED, PARAMETER_SPECS, requested_parameters
from vlm_vpr_ros.runtime.worker import MAX_WAITERS
from vlm_vpr_ros.ros.malloc import tune_malloc
from vlm_vpr_ros.ros.requests import DRAIN_S
from vlm_vpr_ros.ros.wiring import _Wiring
from vlm_vpr_ros.redact import redact

NODE_NAME = "vlm_vpr_node"
#: executor threads: images, diagnostics, map_reload, parameter services + waiting callers
EXECUTOR_THREADS = 4 + MAX_WAITERS


class _RosLogHandler(logging.Handler):
    """Forwards the package's Python log records to the node's rclpy logger (/rosout)."""

    def __init__(self, logger) -> None:
        super().__init__()
        self._logger = logger

    def emit(self, record: logging.LogRecord) -> None:
        text = f"[{record.name}] {record.getMessage()}"
        if record.exc_info and record.exc_info[1] is not None:
            text += f": {record.exc_info[1]!r}"
        text = redact(text)  # the one redaction point (vlm_vpr_ros.redact)
        if record.levelno >= logging.ERROR:
            self._logger.error(text)
        elif record.levelno >= logging.WARNING:
            self._logger.warning(text)
        elif record.levelno >= logging.INFO:
            self._logger.info(text)
        else:
            self._logger.debug(text)


class VlmVprNode(_Wiring, Node):
    """The plain node: configured and active from its constructor until it is destroyed."""

    def __init__(self, requested: dict[str, Any] | None = None, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.finished = Future()  # never done: the plain node runs until SIGINT/SIGTERM
        self.cfg = self._declare_parameters(requested)
        self._load(self.create_publisher)
        self._start()

    def close(self) -> None:
        self._unload()


class VlmVprLifecycleNode(_Wiring, LifecycleNode):
    """The managed node: ``configure`` loads the map and the prior provider, ``activate``
    starts intake and publishing, ``deactivate`` stops them (the map stays loaded),
    ``cleanup`` frees the map. Parameters are declared (and checked) in the constructor."""

    _map_dir_checked_at_start = False  # a missing map_dir fails configure, not start-up

    def __init__(self, requested: dict[str, Any] | None = None, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.finished = Future()  # done after the shutdown transition: the process ends
        self.cfg = self._declare_parameters(requested)

    def _release(self) -> None:
        """cleanup: map, provider, services, timer and the lifecycle publishers."""
        self._unload()
        if self.outputs is not None:
            for pub in self.outputs.managed():
                self.destroy_lifecycle_publisher(pub)
            self.outputs = None

    def _transition(self, what: str, step) -> TransitionCallbackReturn:
        try:
            step()
        except VlmVprError as exc:
            self.get_logger().error(f"{what} failed: {exc}")
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        def load() -> None:
            try:
                self._load(self.create_lifecycle_publisher)
            except VlmVprError:
                self._release()
                raise
        return self._transition("configure", load)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        result = self._transition("activate", self._start)
        if result == TransitionCallbackReturn.SUCCESS:
            super().on_activate(state)  # enables the lifecycle publishers
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop()
        self.get_logger().info("deactivated: intake and publishing stopped, map kept")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        self.get_logger().info("cleaned up: map and prior provider released")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        self.get_logger().info("shut down: the process ends")
        # end the spin once the change_state answer is out (rclpy's executor.shutdown does
        # not wait for running callbacks)
        threading.Timer(0.3, lambda: self.finished.done() or self.finished.set_result(True)
                        ).start()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def close(self) -> None:
        self._unload()


def _fatal(logger, exc: Exception) -> int:
    logger.fatal(redact(f"invalid configuration, not starting: {exc}"))
    rclpy.try_shutdown()
    return 2


def usage(lifecycle: bool = False) -> str:
    """``--help``: how to start the node and every parameter (name, type, default, range or
    choices, runtime-writable, description), from the schema the node declares."""
    exe = "vlm_vpr_lifecycle_node" if lifecycle else "vlm_vpr_node"
    lines = [f"usage: {exe} [--help] --ros-args -p map_dir:=MAP [-p name:=value ...] "
             "[--params-file FILE]",
             "       launch_scripts/run_node.sh [--lifecycle] [PARAMS.yaml] [ros-args...]",
             "", "Image in, NavSatFix (fix), pose, /diagnostics out; relocalize services and "
             "action (docs/node.md).", "", "parameters (* = may change at run time):"]
    for spec in PARAMETER_SPECS.values():
        extra = ""
        if spec.choices:
            extra = f" {{{', '.join(spec.choices)}}}"
        elif spec.range is not None:
            extra = f" [{spec.range[0]:g}, {spec.range[1]:g}]"
        mark = " " if spec.read_only else "*"
        lines.append(f" {mark} {spec.name} ({spec.kind}, default {spec.default!r}){extra}")
        lines.append(f"      {spec.doc}")
    lines.append("   " + ", ".join(f"{n}.<setting>" for n in NESTED) + " (nested settings: "
                 "prior provider, descriptor, verification's features and matcher)")
    return "\n".join(lines)


def _wants_help(argv: list[str]) -> bool:
    """``--help`` / ``-h`` before any ``--ros-args`` (after it they are ROS's)."""
    head = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    return any(a in ("--help", "-h") for a in head)


def _run(cls: type, args: list[str] | None) -> int:
    argv = list(sys.argv if args is None else args)
    if _wants_help(argv):
        print(usage(cls is VlmVprLifecycleNode))
        return 0
    tune_malloc()  # before any thread starts (RSS flat under a camera: docs/node.md)
    logger = rclpy.logging.get_logger(NODE_NAME)
    try:  # what the command line asked for (rcl drops a -p whose type clashes with a file)
        requested = requested_parameters(argv, NODE_NAME)
    except ConfigError as exc:
        print(f"[FATAL] [{NODE_NAME}]: invalid configuration, not starting: {exc}",
              file=sys.stderr)
        return 2
    try:  # SIGINT / SIGTERM: ours (_on_signal), so the goals end before the context does
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except _rclpy.RCLError as exc:  # e.g. a malformed --ros-args
        print(f"[FATAL] [{NODE_NAME}]: invalid arguments, not starting: "
              f"{str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    pkg_log = logging.getLogger("vlm_vpr_ros")
    pkg_log.setLevel(logging.INFO)
    pkg_log.addHandler(_RosLogHandler(logger))
    pkg_log.propagate = False
    try:
        node = cls(requested)
    except VlmVprError as exc:
        return _fatal(logger, exc)
    except KeyboardInterrupt:  # SIGINT while the map loads (Python's handler until ours)
        rclpy.try_shutdown()
        return 0
    executor = MultiThreadedExecutor(num_threads=EXECUTOR_THREADS)
    executor.add_node(node)
    signals: list[int] = []

    def _on_signal(signum: int, _frame: Any) -> None:
        signals.append(signum)
        executor.wake()

    previous = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        # not spin_until_future_complete: rclpy's executor adds a done-callback to the future
        # on every callback it dispatches, and node.finished never completes on the plain node
        # (a list growing by ~80 closures a second under a 30 Hz camera)
        node.finished.add_done_callback(lambda _f: executor.wake())
        while rclpy.ok() and not node.finished.done() and not signals:
            executor.spin_once(timeout_sec=0.5)
        _drain(node, executor, signals)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.close()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


def _drain(node: Any, executor: MultiThreadedExecutor, signals: list[int]) -> None:
    """Answer every caller in progress (NOT_ACTIVE) and let the executor send the answers
    and the goals' results before anything is destroyed; at most DRAIN_S (a second signal
    ends it at once)."""
    n_signals = len(signals)
    node.end_requests()
    deadline = time.monotonic() + DRAIN_S
    while (rclpy.ok() and node.requests_in_progress() and time.monotonic() < deadline
           and len(signals) <= n_signals):
        executor.spin_once(timeout_sec=0.05)
    grace = time.monotonic() + 0.3  # the results go out from executor tasks
    while rclpy.ok() and time.monotonic() < grace and len(signals) <= n_signals:
        executor.spin_once(timeout_sec=0.05)


def main(args: list[str] | None = None) -> int:
    """Console script ``vlm_vpr_node`` (``--ros-args -p name:=value`` / ``--params-file``)."""
    if args is None and "--lifecycle" in sys.argv[1:]:  # python -m ...ros.node --lifecycle
        return lifecycle_main([a for a in sys.argv if a != "--lifecycle"])
    return _run(VlmVprNode, args)


def lifecycle_main(args: list[str] | None = None) -> int:
    """Console script ``vlm_vpr_lifecycle_node``: the managed variant (starts unconfigured)."""
    return _run(VlmVprLifecycleNode, args)


if __name__ == "__main__":
    sys.exit(main())
