"""The ROS 2 wiring shared by ``vlm_vpr_node`` and ``vlm_vpr_lifecycle_node`` (see node.py).

:class:`_Wiring` is mixed into an rclpy ``Node`` or ``LifecycleNode``; its steps are the
lifecycle transitions: parameters (constructor, :mod:`vlm_vpr_ros.ros.parameters`), ``_load``
(configure), ``_start`` (activate), ``_stop`` (deactivate), ``_unload`` (cleanup). What goes out
for a query is :mod:`vlm_vpr_ros.ros.publishers`.
"""

from __future__ import annotations

import copy
import functools
import gc
import os
import threading
import time
from typing import Any

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
from sensor_msgs.msg import CompressedImage, Image
from std_srvs.srv import Trigger

from msg_adapters.image import encoded_bytes, message_to_rgb, stamp_ns
from vlm_vpr_ros.errors import ConfigError, MapError
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
from vlm_vpr_ros.priors import create_prior_provider
from vlm_vpr_ros.ros.malloc import trim_malloc
from vlm_vpr_ros.ros.publishers import Outputs, fix_policy
from vlm_vpr_ros.ros.relocalize_server import TypedRelocalize
from vlm_vpr_ros.ros.requests import DRAIN_S, REQUEST_QOS, CallGate
from vlm_vpr_ros.ros.robot_prior import RobotPriorInput
from vlm_vpr_ros.ros.parameters import _Parameters
from vlm_vpr_ros.runtime.params import NodeConfig
from vlm_vpr_ros.runtime.stats import RuntimeStats, Throttle
from vlm_vpr_ros.runtime.worker import (Frame, QueryOutcome, QueryRuntime, RelocalizeKind,
                                        RuntimeConfig, outcome_summary, reload_pipeline)

#: the relocalize services: std_srvs/Trigger has no fields, so one service per kind of request
RELOCALIZE_SERVICES = {
    "relocalize": RelocalizeKind("latest", True),
    "relocalize_next_frame": RelocalizeKind("next", True),
    "relocalize_no_prior": RelocalizeKind("latest", False),
}


def image_qos(name: str, depth: int) -> QoSProfile:
    """The image subscription's QoS: sensor_data (default), best_effort or reliable.

    A best-effort reader matches best-effort *and* reliable writers, so the default receives
    from every camera driver; a reliable reader matches only reliable writers.
    """
    if name == "sensor_data":
        profile = copy.copy(qos_profile_sensor_data)
        profile.depth = depth
        return profile
    rel = ReliabilityPolicy.RELIABLE if name == "reliable" else ReliabilityPolicy.BEST_EFFORT
    return QoSProfile(depth=depth, reliability=rel)


def runtime_config(cfg: NodeConfig) -> RuntimeConfig:
    return RuntimeConfig(cfg.mode, cfg.min_period_s, cfg.prior_timeout_s, cfg.max_frame_age_s)


class _Wiring(_Parameters):
    """The implementation shared by :class:`VlmVprNode` and :class:`VlmVprLifecycleNode`
    (mixed into an rclpy ``Node`` / ``LifecycleNode``)."""

    cfg: NodeConfig
    pipeline: LocalizationPipeline | None = None
    runtime: QueryRuntime | None = None
    outputs: Outputs | None = None
    _provider: Any = None
    _active = False

    # -- clock ------
    def _now_s(self) -> float:
        """Seconds on the node's clock: ROS time under use_sim_time, else monotonic."""
        clock = self.get_clock()
        if clock.ros_time_is_active:
            return clock.now().nanoseconds * 1e-9
        return time.monotonic()

    # -- configure / cleanup ------
    def _load(self, make_publisher) -> None:
        cfg = self.cfg
        t0 = time.monotonic()
        path = os.path.expanduser(cfg.map_dir)
        if not os.path.isdir(path):
            raise MapError(f"map_dir {cfg.map_dir!r} does not exist or is not a folder")
        if not os.access(path, os.R_OK | os.X_OK):
            raise MapError(f"map_dir {cfg.map_dir!r} is not readable by this process")
        self.pipeline = LocalizationPipeline.open(
            path, descriptor=cfg.descriptor or None, localizer=cfg.localizer_config(),
            descriptor_config=cfg.descriptor_options, verify=cfg.verify_map,
            verification=cfg.verification_config(), status=cfg.status_policy())
        self._provider = create_prior_provider(cfg.prior_provider, cfg.prior)
        self.policy = fix_policy(cfg)
        m = self.pipeline.map
        self.outputs = Outputs(self, make_publisher, cfg, m.path, m.manifest)
        self._robot_prior = None
        if cfg.prior_topic:  # the robot's own estimate, the provider as its fallback
            self._robot_prior = RobotPriorInput(self, cfg, self._provider, self.outputs.frame)
            self._provider = self._robot_prior.provider
        self._flag_log = Throttle(10.0)
        self._trim_log = Throttle(60.0)
        self._stats = RuntimeStats(self._provider.name, cfg.mode)
        if cfg.publish_debug:
            self.outputs.ensure_debug()
        # every request path: reentrant + the one deep request queue (ros/requests.py); a
        # caller of a burst waits for the shared query on its own executor thread (node.py
        # sizes the executor for the admission limit), map_reload answers a second caller at
        # once while a reload runs
        reloc_group = ReentrantCallbackGroup()
        self.gate = CallGate()
        self._reloading = threading.Lock()
        self._own_services = [self.create_service(
            Trigger, name, functools.partial(self._on_relocalize, kind),
            qos_profile=REQUEST_QOS, callback_group=reloc_group)
            for name, kind in RELOCALIZE_SERVICES.items()]
        self._own_services.append(self.create_service(
            Trigger, "map_reload", self._on_map_reload, qos_profile=REQUEST_QOS,
            callback_group=ReentrantCallbackGroup()))
        self._typed = TypedRelocalize(self, self.gate)  # relocalize_typed + relocalize action
        self._diag_timer = self.create_timer(cfg.diagnostics_period_s, self._publish_diagnostics,
                                             callback_group=MutuallyExclusiveCallbackGroup())
        self._images_group = MutuallyExclusiveCallbackGroup()
        self._subs: list[Any] = []
        self.get_logger().info(
            f"map loaded in {time.monotonic() - t0:.1f} s: {cfg.map_dir} "
            f"({m.manifest.get('n_references', '?')} references, {len(m.submaps)} submaps, "
            f"descriptor {self.pipeline.descriptor.name}), prior {cfg.prior_provider}")

    def end_requests(self) -> None:
        """Stop admitting callers and answer every waiting one (NOT_ACTIVE): the runtime
        stops. Their answers go out while the executor still spins (node.py drains them)."""
        gate = getattr(self, "gate", None)
        if gate is not None:
            gate.close()
        self._stop()

    def requests_in_progress(self) -> int:
        gate = getattr(self, "gate", None)
        return gate.in_progress if gate is not None else 0

    def _unload(self) -> None:
        self.end_requests()
        if getattr(self, "gate", None) is not None and not self.gate.wait_idle(DRAIN_S):
            self.get_logger().error(f"{self.gate.in_progress} callers still in progress after "
                                    f"{DRAIN_S:g} s: destroying the services anyway")
        if getattr(self, "_diag_timer", None) is not None:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = None
        for srv in getattr(self, "_own_services", []):
            self.destroy_service(srv)
        self._own_services = []
        if getattr(self, "_typed", None) is not None:
            self._typed.destroy()
            self._typed = None
        if getattr(self, "_robot_prior", None) is not None:
            self._robot_prior.destroy()
            self._robot_prior = None
        if self.outputs is not None:
            self.outputs.destroy_debug()
        if self._provider is not None:
            self._provider.close()
            self._provider = None
        self.pipeline = None
        gc.collect()

    # -- activate / deactivate ------
    def _start(self) -> None:
        cfg = self.cfg
        self.runtime = QueryRuntime(
            self.pipeline, self._provider, runtime_config(cfg), decode=message_to_rgb,
            on_outcome=self._publish_outcome, encoded=encoded_bytes, clock=self._now_s,
            stats=self._stats)
        # settings tuned while inactive (lifecycle) reach the new worker too
        self.runtime.update(localizer=cfg.localizer_config(), status=cfg.status_policy(),
                            verify_top_k=cfg.verify_top_k)
        # the decoded frame stays with its outcome until published: a publish_debug turned on
        # at run time draws the very next answer too
        self.runtime.keep_images = True
        topics = []
        try:
            for enabled, msg_type, topic in ((cfg.subscribe_raw, Image, "image"),
                                             (cfg.subscribe_compressed, CompressedImage,
                                              "image/compressed")):
                if enabled:
                    self._subs.append(self.create_subscription(
                        msg_type, topic, self._on_image, image_qos(cfg.qos, cfg.qos_depth),
                        callback_group=self._images_group,
                        qos_overriding_options=QoSOverridingOptions.with_default_policies()))
                    topics.append(self.resolve_topic_name(topic))
        except (InvalidQosOverridesError, ValueError, KeyError, TypeError) as exc:
            for sub in self._subs:
                self.destroy_subscription(sub)
            self._subs = []
            raise ConfigError(f"invalid qos_overrides for the image subscription: {exc}") \
                from None
        self.runtime.start()
        self._active = True
        qos = self._subs[0].qos_profile if self._subs else None
        rel = qos.reliability.name.lower() if qos is not None else "?"
        self.get_logger().info(
            f"localizing: mode {cfg.mode}, images {', '.join(topics)} ({cfg.qos}: {rel}, depth "
            f"{qos.depth if qos is not None else '?'}), fixes on "
            f"{self.resolve_topic_name('fix')} ({cfg.fix_durability})")

    def _stop(self) -> None:
        self._active = False
        for sub in getattr(self, "_subs", []):
            self.destroy_subscription(sub)
        self._subs = []
        if self.runtime is not None:
            self.runtime.stop(close_provider=False)
            self.pipeline = self.runtime.pipeline  # as map_reload may have swapped it
            self.runtime = None

    def _settings_changed(self) -> None:
        """Runtime tuning (ros/parameters.py): pass the new settings on."""
        cfg = self.cfg
        self.policy = fix_policy(cfg)
        if self.runtime is not None:
            self.runtime.update(runtime_config(cfg), cfg.localizer_config(),
                                cfg.status_policy(), cfg.verify_top_k)
        if self._stats is not None:
            self._stats.mode = cfg.mode
        if cfg.publish_debug and self.outputs is not None:
            self.outputs.ensure_debug()

    _stats: RuntimeStats | None = None

    # -- callbacks -----
    def _on_image(self, msg) -> None:
        runtime = self.runtime
        if runtime is None:
            return
        stamp = stamp_ns(msg) or self.get_clock().now().nanoseconds
        runtime.on_frame(Frame(msg, stamp, str(msg.header.frame_id)))

    def _on_relocalize(self, kind: RelocalizeKind, request, response):
        runtime = self.runtime
        if runtime is None or not self._active or not self.gate.enter():
            response.success = False
            response.message = f"{self.get_name()} is not active: activate it first"
            return response
        try:
            response.success, response.message = runtime.relocalize(
                self.cfg.relocalize_wait_s, self.resolve_topic_name("fix"), kind)
        finally:
            self.gate.leave()
        return response

    def _on_map_reload(self, request, response):
        """Swap in the map re-read from map_dir (e.g. grown by 'vlm-vpr map add') between two
        queries; on failure the current map stays in use. Inactive: reloaded for activate.
        One reload at a time: a call during a reload is answered at once (call again)."""
        if not self._reloading.acquire(blocking=False):
            response.success = False
            response.message = ("busy: a map reload is already running; call map_reload again "
                                "when it has answered to read changes made since it started")
            return response
        try:
            return self._map_reload(response)
        finally:
            self._reloading.release()

    def _map_reload(self, response):
        runtime = self.runtime
        if runtime is not None:
            response.success, response.message = runtime.reload_map()
            self.pipeline = runtime.pipeline
            return response
        new, why = (reload_pipeline(self.pipeline) if self.pipeline is not None
                    else (None, "no map loaded: configure first"))
        if new is None:
            response.success, response.message = False, f"map reload failed: {why}"
            return response
        self.pipeline = new
        response.success, response.message = True, (
            f"map {self.cfg.map_dir} reloaded: {new.map.n_references} references (used from "
            "the next activate)")
        return response

    # -- output -----
    def _publish_outcome(self, out: QueryOutcome) -> None:
        if not self._active or self.outputs is None:
            return
        cfg, hyp = self.cfg, out.hypothesis
        self.outputs.publish(out, cfg, self.policy)
        if hyp is not None:  # one level per kind of answer; a throttle only drops lines
            summary = outcome_summary(out, 0.0)[1]  # "fix for frame ..." in continuous mode
            if hyp.flagged:
                if self._flag_log.ready():
                    self.get_logger().warning(summary)
            elif out.trigger == "relocalize":
                self.get_logger().info(summary)
            else:
                self.get_logger().debug(summary)
        elif not out.error.startswith("undecodable"):
            self.get_logger().error(f"no fix for frame {out.frame.key}: {out.error}")
        self._publish_diagnostics()

    def _publish_diagnostics(self) -> None:
        if not self._active or self.pipeline is None or self.outputs is None:
            return
        if self._trim_log.ready():  # freed image and feature buffers back to the OS
            trim_malloc()
        runtime = self.runtime
        level, message, values = self._stats.report(busy=bool(runtime and runtime.busy))
        pipe = runtime.pipeline if runtime is not None else self.pipeline
        values = {"map_dir": self.cfg.map_dir, "descriptor": pipe.descriptor.name,
                  "fusion": self.cfg.fusion, "calibration": pipe.localizer.calibration_source,
                  "verification": pipe.verifier.unavailable or "on, p_correct calibrated by "
                  + pipe.verifier.calibration_source,
                  "map_references": pipe.map.n_references,
                  "map_generation": pipe.map.manifest.get("generation", 0), **values}
        robot = getattr(self, "_robot_prior", None)
        if robot is not None:  # the robot's own estimate as the prior (prior_topic)
            values["prior_topic_used"] = robot.provider.used
            values["prior_topic_rejected"] = robot.provider.rejected
        self.outputs.publish_diagnostics(self.get_clock().now().nanoseconds, level, message,
                                         values, self.cfg.hardware_id)
