"""``vlm-vpr replay``: publish a bag's serialized messages onto live ROS 2 topics.

Messages go out as recorded CDR bytes through real rclpy publishers (no deserialization), with
their recorded relative timing divided by ``rate``. Before the first message the replayer waits
(bounded) until every replayed topic has a subscriber, so a node started alongside it loses
nothing; publishers use the QoS recorded in the bag when it is readable. Ctrl-C stops cleanly.
rclpy is imported lazily, inside :func:`replay_bag`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from vlm_vpr_ros.bags.msgdefs import message_class
from vlm_vpr_ros.bags.reader import BagReader, TopicInfo
from vlm_vpr_ros.errors import BagError, ConfigError

log = logging.getLogger(__name__)


@dataclass
class ReplayConfig:
    rate: float = 1.0  # playback speed factor (2.0: twice as fast)
    loop: bool = False
    topics: list[str] | None = None  # bag topics to replay (default: all with a known type)
    remap: dict[str, str] = field(default_factory=dict)  # bag topic → published topic
    wait_subscribers_s: float = 5.0  # wait this long for a subscriber on every topic
    linger_s: float = 0.5  # keep the publishers alive this long after the last message
    domain_id: int | None = None  # None: ROS_DOMAIN_ID from the environment

    def __post_init__(self) -> None:
        if not (self.rate > 0 and self.rate < 1e6):
            raise ConfigError(f"replay rate must be a positive factor, got {self.rate}")
        if self.wait_subscribers_s < 0 or self.linger_s < 0:
            raise ConfigError("wait and linger times must be >= 0")


def parse_remaps(items: list[str] | None) -> dict[str, str]:
    """``["/a:=/b", ...]`` → ``{"/a": "/b"}``."""
    out = {}
    for item in items or []:
        src, sep, dst = item.partition(":=")
        if not sep or not src or not dst:
            raise ConfigError(f"expected a remap FROM:=TO, got {item!r}")
        out[src] = dst
    return out


def _qos(info: TopicInfo) -> Any:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    prof = info.qos[0] if info.qos else {}
    rel = str(prof.get("reliability", "reliable")).lower()
    dur = str(prof.get("durability", "volatile")).lower()
    depth = prof.get("depth", 10)
    depth = depth if isinstance(depth, int) and depth > 0 else 10
    return QoSProfile(
        depth=max(10, depth),
        reliability=(ReliabilityPolicy.BEST_EFFORT if rel in ("best_effort", "2")
                     else ReliabilityPolicy.RELIABLE),
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if dur in ("transient_local", "1")
                    else DurabilityPolicy.VOLATILE))


def select_topics(bag: BagReader, config: ReplayConfig) -> dict[str, tuple[TopicInfo, Any]]:
    """Bag topic → (info, message class) for the topics that will be published."""
    names = config.topics or sorted(bag.topics)
    unknown = [t for t in names if t not in bag.topics]
    if unknown:
        raise BagError(f"{bag.path}: no topic(s) {unknown}; the bag has: {bag.describe()}")
    out = {}
    for name in names:
        info = bag.topics[name]
        try:
            out[name] = (info, message_class(info.type))
        except BagError as exc:
            log.warning("not replaying %s: %s", name, exc)
    if not out:
        raise BagError(f"{bag.path}: none of the topics can be published here; the bag has: "
                       f"{bag.describe()}")
    return out


def _sleep_until(deadline: float) -> None:
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(left, 0.05))


def replay_bag(bag: BagReader, config: ReplayConfig | None = None,
               on_progress: Callable[[int, int, float], None] | None = None) -> dict:
    """Publish the bag (once, or until interrupted with ``loop``); returns counts and times.
    ``on_progress(published, total, bag_seconds)`` is called after every message."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    cfg = config or ReplayConfig()
    chosen = select_topics(bag, cfg)
    total = sum(info.count or 0 for info, _ in chosen.values())
    ctx = Context()
    rclpy.init(context=ctx, domain_id=cfg.domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    node = None
    stats: dict[str, Any] = {"published": 0, "loops": 0, "topics": {}}
    try:
        node = Node("vlm_vpr_replay", context=ctx, start_parameter_services=False)
        pubs = {name: node.create_publisher(cls, cfg.remap.get(name, name), _qos(info))
                for name, (info, cls) in chosen.items()}
        stats["topics"] = {name: cfg.remap.get(name, name) for name in pubs}
        _wait_for_subscribers(pubs, cfg.wait_subscribers_s)
        t_wall0 = time.monotonic()
        while True:
            stats["loops"] += 1
            start = time.monotonic()
            first = None
            for i, msg in enumerate(bag.messages(list(pubs))):
                first = msg.log_time_ns if first is None else first
                offset = (msg.log_time_ns - first) / 1e9
                _sleep_until(start + offset / cfg.rate)
                pubs[msg.topic].publish(msg.data)
                stats["published"] += 1
                if on_progress:
                    on_progress(i + 1, total, offset)
            if not cfg.loop or first is None:
                break
        _sleep_until(time.monotonic() + cfg.linger_s)
        stats["wall_s"] = round(time.monotonic() - t_wall0, 3)
    finally:
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()
    return stats


def _wait_for_subscribers(pubs: dict[str, Any], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if all(p.get_subscription_count() > 0 for p in pubs.values()):
            return
        time.sleep(0.05)
    lonely = sorted(n for n, p in pubs.items() if p.get_subscription_count() == 0)
    if lonely and timeout_s > 0:
        log.info("no subscriber after %.1f s on %s; publishing anyway", timeout_s,
                 ", ".join(lonely))
