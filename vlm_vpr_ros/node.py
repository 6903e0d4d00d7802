"""``vlm_vpr_node``: Image in, NavSatFix + diagnostics out (ROS 2 wiring only).

The query logic lives in :mod:`vlm_vpr_ros.runtime` (pure), message conversions in
:mod:`msg_adapters`, the parameter schema in :mod:`vlm_vpr_ros.node_config`. Callback groups:
images, the relocalize and map_reload services and the diagnostics timer each have their own
mutually exclusive group under a MultiThreadedExecutor; queries run on the runtime's worker
thread, so a slow VLM never delays image intake and a waiting service call never blocks the
executor.
"""

from __future__ import annotations

import copy
import logging
import os
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CompressedImage, Image, NavSatFix
from std_srvs.srv import Trigger

from msg_adapters.diagnostics import diagnostic_array
from msg_adapters.image import encoded_bytes, message_to_rgb, stamp_ns
from msg_adapters.navsat import FixPolicy, navsat_fix
from vlm_vpr_ros.errors import VlmVprError
from vlm_vpr_ros.node_config import PARAMETERS, from_params
from vlm_vpr_ros.pipeline import LocalizationPipeline
from vlm_vpr_ros.priors import create_prior_provider
from vlm_vpr_ros.runtime import (Frame, QueryOutcome, QueryRuntime, RuntimeConfig,
                                 outcome_summary)
from vlm_vpr_ros.runtime_stats import Throttle

NODE_NAME = "vlm_vpr_node"


def image_qos(name: str, depth: int) -> QoSProfile:
    """The image subscription's QoS: reliable (default), best_effort or sensor_data."""
    if name == "sensor_data":
        profile = copy.copy(qos_profile_sensor_data)
        profile.depth = depth
        return profile
    rel = ReliabilityPolicy.RELIABLE if name == "reliable" else ReliabilityPolicy.BEST_EFFORT
    return QoSProfile(depth=depth, reliability=rel)


class _RosLogHandler(logging.Handler):
    """Forwards the package's Python log records to the node's rclpy logger (/rosout)."""

    def __init__(self, logger) -> None:
        super().__init__()
        self._logger = logger

    def emit(self, record: logging.LogRecord) -> None:
        text = f"[{record.name}] {record.getMessage()}"
        if record.exc_info and record.exc_info[1] is not None:
            text += f": {record.exc_info[1]!r}"
        if record.levelno >= logging.ERROR:
            self._logger.error(text)
        elif record.levelno >= logging.WARNING:
            self._logger.warning(text)
        elif record.levelno >= logging.INFO:
            self._logger.info(text)
        else:
            self._logger.debug(text)


class VlmVprNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, automatically_declare_parameters_from_overrides=True,
                         **kwargs)
        for name, (default, doc) in PARAMETERS.items():
            if not self.has_parameter(name):
                self.declare_parameter(name, default, ParameterDescriptor(description=doc))
        params = self.get_parameters_by_prefix("")
        cfg = self.cfg = from_params({k: p.value for k, p in params.items()})
        t0 = time.monotonic()
        self.pipeline = LocalizationPipeline.open(
            os.path.expanduser(cfg.map_dir), descriptor=cfg.descriptor or None,
            localizer=cfg.localizer_config(), descriptor_config=cfg.descriptor_options)
        provider = create_prior_provider(cfg.prior_provider, cfg.prior)
        self.policy = FixPolicy(cfg.fallback_status, cfg.fallback_min_sigma_m, cfg.altitude_m,
                                cfg.altitude_sigma_m)
        self._flag_log = Throttle(10.0)
        self.fix_pub = self.create_publisher(NavSatFix, "fix", 10)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.runtime = QueryRuntime(
            self.pipeline, provider,
            RuntimeConfig(cfg.mode, cfg.min_period_s, cfg.prior_timeout_s, cfg.max_frame_age_s),
            decode=message_to_rgb, on_outcome=self._publish_outcome, encoded=encoded_bytes)
        images = MutuallyExclusiveCallbackGroup()
        qos = image_qos(cfg.qos, cfg.qos_depth)
        topics = []
        if cfg.subscribe_raw:
            self.create_subscription(Image, "image", self._on_image, qos, callback_group=images)
            topics.append(self.resolve_topic_name("image"))
        if cfg.subscribe_compressed:
            self.create_subscription(CompressedImage, "image/compressed", self._on_image, qos,
                                     callback_group=images)
            topics.append(self.resolve_topic_name("image/compressed"))
        self.create_service(Trigger, "relocalize", self._on_relocalize,
                            callback_group=MutuallyExclusiveCallbackGroup())
        self.create_service(Trigger, "map_reload", self._on_map_reload,
                            callback_group=MutuallyExclusiveCallbackGroup())
        self.create_timer(cfg.diagnostics_period_s, self._publish_diagnostics,
                          callback_group=MutuallyExclusiveCallbackGroup())
        self.add_on_set_parameters_callback(self._reject_changes)
        self.runtime.start()
        m = self.pipeline.map
        self.get_logger().info(
            f"ready in {time.monotonic() - t0:.1f} s: map {cfg.map_dir} "
            f"({m.manifest.get('n_references', '?')} references, {len(m.submaps)} submaps, "
            f"descriptor {self.pipeline.descriptor.name}), "
            f"prior {cfg.prior_provider}, mode {cfg.mode}, images {', '.join(topics)} "
            f"({cfg.qos}, depth {cfg.qos_depth})")

    # -- callbacks -----
    def _on_image(self, msg) -> None:
        stamp = stamp_ns(msg) or self.get_clock().now().nanoseconds
        self.runtime.on_frame(Frame(msg, stamp, str(msg.header.frame_id)))

    def _on_relocalize(self, request, response):
        t0 = time.monotonic()
        ticket = self.runtime.request_relocalize()
        if self.cfg.relocalize_wait_s <= 0:
            response.success = True
            response.message = ("relocalization scheduled on the latest or next frame; the fix "
                                f"will be published on {self.resolve_topic_name('fix')}")
            return response
        outcome = ticket.wait(self.cfg.relocalize_wait_s)
        response.success, response.message = outcome_summary(outcome, time.monotonic() - t0)
        return response

    def _on_map_reload(self, request, response):
        """Swap in the map re-read from map_dir (e.g. grown by 'vlm-vpr map add') between two
        queries; on failure the current map stays in use."""
        response.success, response.message = self.runtime.reload_map()
        self.pipeline = self.runtime.pipeline
        return response

    def _reject_changes(self, params) -> SetParametersResult:
        return SetParametersResult(
            successful=False, reason=f"{NODE_NAME} reads its parameters at start-up; restart "
                                     "it with the new values")

    # -- output -----
    def _publish_outcome(self, out: QueryOutcome) -> None:
        hyp = out.hypothesis
        if hyp is not None:
            frame_id = self.cfg.frame_id or out.frame.frame_id
            self.fix_pub.publish(navsat_fix(hyp, out.frame.stamp_ns, frame_id, self.policy))
            summary = outcome_summary(out, 0.0)[1]
            if hyp.flagged and self._flag_log.ready():
                self.get_logger().warning(summary)
            elif out.trigger == "relocalize":
                self.get_logger().info(summary)
            else:
                self.get_logger().debug(summary)
        elif not out.error.startswith("undecodable"):
            self.get_logger().error(f"no fix for frame {out.frame.key}: {out.error}")
        self._publish_diagnostics()

    def _publish_diagnostics(self) -> None:
        level, message, values = self.runtime.stats.report(busy=self.runtime.busy)
        m = self.runtime.pipeline.map
        values = {"map_dir": self.cfg.map_dir, "descriptor": self.pipeline.descriptor.name,
                  "map_references": m.n_references,
                  "map_generation": m.manifest.get("generation", 0), **values}
        self.diag_pub.publish(diagnostic_array(
            self.get_clock().now().nanoseconds, f"{self.get_name()}: VPR geo-localization",
            self.cfg.hardware_id, level, message, values))


def main(args: list[str] | None = None) -> int:
    """Console script ``vlm_vpr_node`` (``--ros-args -p name:=value`` / ``--params-file``)."""
    rclpy.init(args=args)
    logger = rclpy.logging.get_logger(NODE_NAME)
    pkg_log = logging.getLogger("vlm_vpr_ros")
    pkg_log.setLevel(logging.INFO)
    pkg_log.addHandler(_RosLogHandler(logger))
    pkg_log.propagate = False
    try:
        node = VlmVprNode()
    except VlmVprError as exc:
        logger.fatal(f"invalid configuration, not starting: {exc}")
        rclpy.try_shutdown()
        return 2
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.runtime.stop()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
