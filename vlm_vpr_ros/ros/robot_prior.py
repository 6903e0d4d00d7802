"""``prior_topic``: the subscription that feeds the robot's own estimate to the prior (ROS edge).

Messages are converted by :mod:`msg_adapters.robot_prior`, checked and aged by the pure
:class:`~vlm_vpr_ros.priors.robot.TopicPrior` (which also holds the fallback provider). A message
that cannot be used (NaN / zero / negative covariance, a stamp in the future or older than
``prior_topic_max_age_s``, a frame the node cannot convert, no fix) is ignored with one WARN per
kind of problem naming it, and counted; it never becomes a prior.
"""

from __future__ import annotations

from typing import Any

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import QoSProfile, ReliabilityPolicy

from msg_adapters.robot_prior import estimate_from_msg, message_class
from vlm_vpr_ros.errors import VlmVprError
from vlm_vpr_ros.priors.provider import PriorProvider
from vlm_vpr_ros.priors.robot import TopicPrior, TopicPriorConfig


class RobotPriorInput:
    """The subscription and the provider it feeds (made at configure, gone at cleanup)."""

    def __init__(self, node: Any, cfg: Any, fallback: PriorProvider, frame: Any) -> None:
        self.node, self.kind, self.frame = node, cfg.prior_topic_type, frame
        self.topic = node.resolve_topic_name(cfg.prior_topic)
        config = TopicPriorConfig(cfg.prior_topic_growth_m_per_s, cfg.prior_topic_max_age_s,
                                  order=cfg.prior_order)
        # stamps are ROS time (sim time under use_sim_time): compare them on the ROS clock
        self.provider = TopicPrior(fallback, config, clock=self._now, label=self.topic)
        # a best-effort reader matches reliable and best-effort writers (GNSS drivers, filters)
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.sub = node.create_subscription(message_class(self.kind), cfg.prior_topic,
                                            self._on_msg, qos,
                                            callback_group=MutuallyExclusiveCallbackGroup())

    def _now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _on_msg(self, msg: Any) -> None:
        try:
            est = estimate_from_msg(self.kind, msg, self.frame, f"{self.kind} {self.topic}")
        except (VlmVprError, ValueError, TypeError, IndexError, AttributeError) as exc:
            self.provider.reject(f"{self.kind} {self.topic}", str(exc))
            return
        self.provider.update(est)

    def destroy(self) -> None:
        self.node.destroy_subscription(self.sub)
