"""What the node publishes for a query: ``fix``, ``pose``, the debug views and /diagnostics.

Publishers are made at configure (``fix``, ``pose``, ``/diagnostics``) with the QoS of
:func:`output_qos`, the debug publishers (``~/debug_image/compressed``, ``~/candidates``:
``vlm_vpr_interfaces/msg/Candidates``) too, so a subscriber is matched before
``publish_debug`` is turned on at run time and receives the picture of every frame processed
from then on; the work (drawing, encoding) is done only while it is on.

Late joiners (``fix_durability: transient_local``): ``fix`` and ``pose`` each keep their last
message, and a fix without a pose (a NO_FIX, a fix that is not a relocalization) would leave an
older pose behind. The pose publisher is then made anew (its kept pose dropped), so a
subscriber that joins later never receives a pose older than the latest fix.
Messages are built by :mod:`msg_adapters`; the pose's metric frame by
:mod:`vlm_vpr_ros.runtime.metric_frame`; the debug picture by
:mod:`vlm_vpr_ros.runtime.debug_view`.
"""

from __future__ import annotations

from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage, NavSatFix
from vlm_vpr_interfaces.msg import Candidates

from msg_adapters.answer import answer_msg, candidates_msg
from msg_adapters.debug import compressed_jpeg
from msg_adapters.diagnostics import diagnostic_array
from msg_adapters.navsat import STATUS_FIX, FixPolicy, fix_fields, navsat_fix
from msg_adapters.pose import pose_with_covariance
from vlm_vpr_ros.errors import VlmVprError
from vlm_vpr_ros.runtime import debug_view
from vlm_vpr_ros.runtime.metric_frame import metric_frame
from vlm_vpr_ros.runtime.params import NodeConfig
from vlm_vpr_ros.runtime.relocalize import RelocalizeResult
from vlm_vpr_ros.runtime.stats import Throttle
from vlm_vpr_ros.runtime.worker import QueryOutcome

DEBUG_IMAGE_TOPIC = "~/debug_image/compressed"
CANDIDATES_TOPIC = "~/candidates"


def output_qos(durability: str) -> QoSProfile:
    """QoS of ``fix`` and ``pose``: reliable; ``transient_local`` keeps the last message for
    late subscribers (depth 1: the last relocalization), ``volatile`` keeps 10 for live ones.
    Both match volatile and transient-local, reliable and best-effort subscribers."""
    if durability == "transient_local":
        return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def fix_policy(cfg: NodeConfig) -> FixPolicy:
    return FixPolicy(cfg.altitude_m, cfg.altitude_sigma_m, cfg.status_policy())


class Outputs:
    """The node's publishers and how one query outcome becomes messages."""

    def __init__(self, node: Any, make_publisher: Callable[..., Any], cfg: NodeConfig,
                 map_path: Any, manifest: dict) -> None:
        self.node = node
        qos = self._qos = output_qos(cfg.fix_durability)
        self._make, self._latched = make_publisher, cfg.fix_durability == "transient_local"
        self._pose_kept = False  # the pose publisher keeps a pose for late joiners
        self.frame = metric_frame(cfg.pose_frame, cfg.pose_frame_id, cfg.utm_zone,
                                  cfg.datum_lat, cfg.datum_lon, cfg.datum_yaw)
        self.fix = make_publisher(NavSatFix, "fix", qos)
        self.pose = (make_publisher(PoseWithCovarianceStamped, "pose", qos)
                     if self.frame is not None else None)
        self.diag = make_publisher(DiagnosticArray, "/diagnostics", 10)
        self.references = debug_view.ReferenceImages.for_map(map_path, manifest,
                                                             cfg.reference_images_dir)
        self.debug_image = self.candidates = None
        self._pose_log = Throttle(10.0)
        self._debug_log = Throttle(30.0)
        self.ensure_debug()

    def managed(self) -> list[Any]:
        """The publishers made with ``make_publisher`` (lifecycle publishers on that node)."""
        return [p for p in (self.fix, self.pose, self.diag) if p is not None]

    def ensure_debug(self) -> None:
        """Create the debug publishers (plain ones: they publish only from active queries)."""
        if self.debug_image is None:
            depth = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
            self.debug_image = self.node.create_publisher(CompressedImage, DEBUG_IMAGE_TOPIC,
                                                          depth)
            self.candidates = self.node.create_publisher(Candidates, CANDIDATES_TOPIC, 10)

    def destroy_debug(self) -> None:
        for pub in (self.debug_image, self.candidates):
            if pub is not None:
                self.node.destroy_publisher(pub)
        self.debug_image = self.candidates = None

    def publish(self, out: QueryOutcome, cfg: NodeConfig, policy: FixPolicy) -> None:
        """fix (+ pose for STATUS_FIX) for a hypothesis; debug views when asked for."""
        hyp, stamp = out.hypothesis, out.frame.stamp_ns
        frame_id = cfg.frame_id or out.frame.frame_id
        fields = None
        if hyp is not None:
            fields = fix_fields(hyp, policy)
            posed = False
            wanted = cfg.pose_on == "every_fix" or out.trigger == "relocalize"
            if self.pose is not None and fields.precise and wanted:  # never a fallback fix
                try:
                    pose = self.frame.pose(fields.latitude, fields.longitude, fields.altitude,
                                           fields.covariance)
                except VlmVprError as exc:
                    if self._pose_log.ready():
                        self.node.get_logger().warning(f"no pose for this fix: {exc}")
                else:
                    posed = True
            if not posed and self._pose_kept:
                self._drop_kept_pose()  # before the fix: a joiner never pairs it with the old
            self.fix.publish(navsat_fix(hyp, stamp, frame_id, fields=fields))
            if posed:
                self.pose.publish(pose_with_covariance(pose, stamp))
                self._pose_kept = self._latched
        if cfg.publish_debug and out.rgb is not None:
            self.ensure_debug()
            self._publish_debug(out, fields, stamp, frame_id, cfg.hardware_id)

    def _drop_kept_pose(self) -> None:
        """Make the pose publisher anew: the pose it kept for late joiners goes with it."""
        node, old = self.node, self.pose
        self.pose = self._make(PoseWithCovarianceStamped, "pose", self._qos)
        if hasattr(node, "destroy_lifecycle_publisher") and hasattr(old, "on_activate"):
            if getattr(node, "_active", False):
                self.pose.on_activate(None)  # a lifecycle publisher starts inactive
            node.destroy_lifecycle_publisher(old)
        else:
            node.destroy_publisher(old)
        self._pose_kept = False

    def _publish_debug(self, out: QueryOutcome, fields: Any, stamp: int, frame_id: str,
                       hardware_id: str) -> None:
        hyp = out.hypothesis
        matches = None
        if hyp is None:
            caption, ref, label = debug_view.caption(None, "", 0.0, out.error), None, ""
        else:
            status = "STATUS_FIX" if fields.status == STATUS_FIX else "STATUS_NO_FIX"
            caption = debug_view.caption(hyp, status, fields.sigma_m)
            ref, label = self.references.load(hyp.ref_id), f"reference {hyp.ref_id}"
            matches = debug_view.match_pixels(out.matches, out.rgb.shape, ref)
        picture = debug_view.render(out.rgb, ref, caption, label, matches)
        try:
            data = debug_view.jpeg(picture)
        except VlmVprError as exc:  # e.g. a picture JPEG cannot hold; the fix is out already
            if self._debug_log.ready():
                self.node.get_logger().warning(
                    f"debug image of frame {out.frame.key} not published: {exc}")
        else:
            self.debug_image.publish(compressed_jpeg(data, stamp, frame_id))
        if hyp is not None:
            self.candidates.publish(candidates_msg(answer_msg(
                RelocalizeResult("answered", out), fields, frame_id)))

    def publish_diagnostics(self, stamp_ns: int, level: str, message: str,
                            values: dict[str, Any], hardware_id: str) -> None:
        self.diag.publish(diagnostic_array(stamp_ns, f"{self.node.get_name()}: VPR "
                                           "geo-localization", hardware_id, level, message,
                                           values))
