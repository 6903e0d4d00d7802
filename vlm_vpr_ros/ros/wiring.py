"""The ROS 2 wiring shared by ``vlm_vpr_node`` and ``vlm_vpr_lifecycle_node`` (see node.py).

:class:`_Wiring` is mixed into an rclpy ``Node`` or ``LifecycleNode``; its steps are the
lifecycle transitions: parameters (constructor), ``_load`` (configure), ``_start`` (activate),
``_stop`` (deactivate), ``_unload`` (cleanup).
"""

from __future__ import annotations

import copy
import gc
import os
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
from sensor_msgs.msg import CompressedImage, Image, NavSatFix
from std_srvs.srv import Trigger

from msg_adapters.diagnostics import diagnostic_array
from msg_adapters.image import encoded_bytes, message_to_rgb, stamp_ns
from msg_adapters.navsat import FixPolicy, navsat_fix
from vlm_vpr_ros.errors import ConfigError, VlmVprError
from vlm_vpr_ros.runtime.params import (NESTED, NodeConfig, PARAMETER_SPECS, ParamSpec,
                                        ROS_STANDARD, from_params, type_conflicts)
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
from vlm_vpr_ros.priors import create_prior_provider
from vlm_vpr_ros.runtime.worker import (Frame, QueryOutcome, QueryRuntime, RuntimeConfig,
                                        outcome_summary)
from vlm_vpr_ros.runtime.stats import RuntimeStats, Throttle

_ROS_TYPES = {"bool": ParameterType.PARAMETER_BOOL, "int": ParameterType.PARAMETER_INTEGER,
              "float": ParameterType.PARAMETER_DOUBLE, "str": ParameterType.PARAMETER_STRING}


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


def parameter_descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The ROS descriptor of one schema parameter (``ros2 param describe`` shows it)."""
    d = ParameterDescriptor(name=spec.name, type=_ROS_TYPES[spec.kind], description=spec.doc,
                            read_only=spec.read_only)
    if spec.choices:
        d.additional_constraints = f"one of: {', '.join(spec.choices)}"
    if spec.range is not None:
        lo, hi = spec.range
        if spec.kind == "int":
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                         to_value=float(hi), step=0.0)]
    return d


class _Wiring:
    """The implementation shared by :class:`VlmVprNode` and :class:`VlmVprLifecycleNode`
    (mixed into an rclpy ``Node`` / ``LifecycleNode``)."""

    cfg: NodeConfig
    pipeline: LocalizationPipeline | None = None
    runtime: QueryRuntime | None = None
    _provider: Any = None
    _active = False

    # -- parameters ------
    def _declare_parameters(self, requested: dict[str, Any] | None) -> NodeConfig:
        """Validate what rclpy received (plus what the command line asked for, which rcl may
        have dropped on a type clash), then declare every parameter once with its descriptor.
        Raises ConfigError on any bad name, type or value."""
        overrides: dict[str, Parameter] = self._parameter_overrides  # rclpy: -p, params files
        received = {k: p.value for k, p in overrides.items()}
        values = {**received, **(requested or {})}
        ours = {k: v for k, v in values.items()
                if k not in ROS_STANDARD and not k.startswith("qos_overrides.")}
        cfg = from_params(ours)
        clashes = type_conflicts(requested or {}, received)
        if clashes:
            raise ConfigError(clashes[0])
        for name, spec in PARAMETER_SPECS.items():
            if name in overrides:  # the validated value (ints given for floats become floats)
                overrides[name] = Parameter(name, value=getattr(cfg, name))
            self.declare_parameter(name, spec.default, parameter_descriptor(spec))
        for key in sorted(k for k in ours if k.partition(".")[0] in NESTED):
            head = key.partition(".")[0]
            self.declare_parameter(key, overrides[key].value if key in overrides else ours[key],
                                   ParameterDescriptor(
                                       description=f"{head} setting (see docs/node.md)",
                                       read_only=True, dynamic_typing=True))
        return cfg

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
        self.pipeline = LocalizationPipeline.open(
            os.path.expanduser(cfg.map_dir), descriptor=cfg.descriptor or None,
            localizer=cfg.localizer_config(), descriptor_config=cfg.descriptor_options,
            verify=cfg.verify_map)
        self._provider = create_prior_provider(cfg.prior_provider, cfg.prior)
        self.policy = FixPolicy(cfg.fallback_status, cfg.fallback_min_sigma_m, cfg.altitude_m,
                                cfg.altitude_sigma_m, cfg.fix_max_sigma_m)
        self._flag_log = Throttle(10.0)
        self._stats = RuntimeStats(self._provider.name, cfg.mode)
        self.fix_pub = make_publisher(NavSatFix, "fix", 10)
        self.diag_pub = make_publisher(DiagnosticArray, "/diagnostics", 10)
        group = MutuallyExclusiveCallbackGroup
        # reentrant + a deep request queue: a burst of calls all get an answer (the runtime
        # lets two wait for the shared query and answers the others at once)
        self._reloc_srv = self.create_service(
            Trigger, "relocalize", self._on_relocalize,
            qos_profile=QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE),
            callback_group=ReentrantCallbackGroup())
        self._reload_srv = self.create_service(Trigger, "map_reload", self._on_map_reload,
                                               callback_group=group())
        self._diag_timer = self.create_timer(cfg.diagnostics_period_s, self._publish_diagnostics,
                                             callback_group=group())
        self._images_group = MutuallyExclusiveCallbackGroup()
        self._subs: list[Any] = []
        m = self.pipeline.map
        self.get_logger().info(
            f"map loaded in {time.monotonic() - t0:.1f} s: {cfg.map_dir} "
            f"({m.manifest.get('n_references', '?')} references, {len(m.submaps)} submaps, "
            f"descriptor {self.pipeline.descriptor.name}), prior {cfg.prior_provider}")

    def _unload(self) -> None:
        self._stop()
        if getattr(self, "_diag_timer", None) is not None:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = None
        for attr in ("_reloc_srv", "_reload_srv"):
            if getattr(self, attr, None) is not None:
                self.destroy_service(getattr(self, attr))
                setattr(self, attr, None)
        if self._provider is not None:
            self._provider.close()
            self._provider = None
        self.pipeline = None
        gc.collect()

    # -- activate / deactivate ------
    def _start(self) -> None:
        cfg = self.cfg
        self.runtime = QueryRuntime(
            self.pipeline, self._provider,
            RuntimeConfig(cfg.mode, cfg.min_period_s, cfg.prior_timeout_s, cfg.max_frame_age_s),
            decode=message_to_rgb, on_outcome=self._publish_outcome, encoded=encoded_bytes,
            clock=self._now_s, stats=self._stats)
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
            f"{self.resolve_topic_name('fix')}")

    def _stop(self) -> None:
        self._active = False
        for sub in getattr(self, "_subs", []):
            self.destroy_subscription(sub)
        self._subs = []
        if self.runtime is not None:
            self.runtime.stop(close_provider=False)
            self.pipeline = self.runtime.pipeline  # as map_reload may have swapped it
            self.runtime = None

    # -- callbacks -----
    def _on_image(self, msg) -> None:
        runtime = self.runtime
        if runtime is None:
            return
        stamp = stamp_ns(msg) or self.get_clock().now().nanoseconds
        runtime.on_frame(Frame(msg, stamp, str(msg.header.frame_id)))

    def _on_relocalize(self, request, response):
        runtime = self.runtime
        if runtime is None or not self._active:
            response.success = False
            response.message = f"{self.get_name()} is not active: activate it first"
            return response
        response.success, response.message = runtime.relocalize(
            self.cfg.relocalize_wait_s, self.resolve_topic_name("fix"))
        return response

    def _on_map_reload(self, request, response):
        """Swap in the map re-read from map_dir (e.g. grown by 'vlm-vpr map add') between two
        queries; on failure the current map stays in use. Inactive: reloaded for activate."""
        runtime = self.runtime
        if runtime is not None:
            response.success, response.message = runtime.reload_map()
            self.pipeline = runtime.pipeline
            return response
        try:
            if self.pipeline is None:
                raise ConfigError("no map loaded: configure first")
            self.pipeline = self.pipeline.reloaded()
            response.success, response.message = True, (
                f"map {self.cfg.map_dir} reloaded: {self.pipeline.map.n_references} "
                "references (used from the next activate)")
        except VlmVprError as exc:
            response.success, response.message = False, f"map reload failed: {exc}"
        return response

    # -- output -----
    def _publish_outcome(self, out: QueryOutcome) -> None:
        if not self._active:
            return
        hyp = out.hypothesis
        if hyp is not None:
            frame_id = self.cfg.frame_id or out.frame.frame_id
            self.fix_pub.publish(navsat_fix(hyp, out.frame.stamp_ns, frame_id, self.policy))
            summary = outcome_summary(out, 0.0)[1]  # "fix for frame ..." in continuous mode
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
        if not self._active or self.pipeline is None:
            return
        runtime = self.runtime
        level, message, values = self._stats.report(busy=bool(runtime and runtime.busy))
        pipe = runtime.pipeline if runtime is not None else self.pipeline
        values = {"map_dir": self.cfg.map_dir, "descriptor": pipe.descriptor.name,
                  "fusion": self.cfg.fusion, "calibration": pipe.localizer.calibration_source,
                  "map_references": pipe.map.n_references,
                  "map_generation": pipe.map.manifest.get("generation", 0), **values}
        self.diag_pub.publish(diagnostic_array(
            self.get_clock().now().nanoseconds, f"{self.get_name()}: VPR geo-localization",
            self.cfg.hardware_id, level, message, values))
