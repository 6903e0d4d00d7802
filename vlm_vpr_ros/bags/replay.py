"""``vlm-vpr replay``: publish a bag's serialized messages onto live ROS 2 topics.

Messages go out as recorded CDR bytes through real rclpy publishers (no deserialization), with
their recorded relative timing divided by ``rate``. Before the first message the replayer waits
(bounded) until every replayed topic has a subscriber, so a node started alongside it loses
nothing; publishers use the QoS recorded in the bag when it is readable. Ctrl-C stops cleanly.
With ``clock_hz`` the replayer also publishes ``/clock`` (``rosgraph_msgs/Clock``, best effort,
depth 1, as ``ros2 bag play --clock`` does): the bag's log time, at that rate while it waits and
right before every message, so nodes with ``use_sim_time`` run on the bag's time (a new pass of
``loop`` makes the clock jump back to the bag's start).
rclpy is imported lazily, inside :func:`replay_bag`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from vlm_vpr_ros.bags.messages import message_class
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
    clock_hz: float | None = None  # publish /clock at this rate (None: no /clock)

    def __post_init__(self) -> None:
        if not (self.rate > 0 and self.rate < 1e6):
            raise ConfigError(f"replay rate must be a positive factor, got {self.rate}")
        if self.wait_subscribers_s < 0 or self.linger_s < 0:
            raise ConfigError("wait and linger times must be >= 0")
        if self.clock_hz is not None and not (0 < self.clock_hz <= 10_000):
            raise ConfigError(f"--clock rate must be in (0, 10000] Hz, got {self.clock_hz}")


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


def _sleep_until(deadline: float, tick: Callable[[], None] | None = None,
                 period_s: float = 0.05) -> None:
    """Sleep until ``deadline`` (monotonic), calling ``tick`` every ``period_s`` meanwhile."""
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(left, period_s))
        if tick is not None and deadline - time.monotonic() > 0:
            tick()


class _Clock:
    """Publishes the bag's time on /clock: ``bag_t0 + (now - wall_t0) * rate``."""

    def __init__(self, node: Any, rate: float) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        self._cls, self.rate = Clock, rate
        self.pub = node.create_publisher(Clock, "/clock", QoSProfile(
            depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.bag_t0, self.wall_t0, self.published = 0, time.monotonic(), 0

    def restart(self, bag_t0_ns: int) -> None:
        self.bag_t0, self.wall_t0 = int(bag_t0_ns), time.monotonic()

    def publish(self, t_ns: int | None = None) -> None:
        if t_ns is None:
            t_ns = self.bag_t0 + int((time.monotonic() - self.wall_t0) * self.rate * 1e9)
        msg = self._cls()
        msg.clock.sec, msg.clock.nanosec = divmod(int(t_ns), 1_000_000_000)
        self.pub.publish(msg)
        self.published += 1


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
        clock = _Clock(node, cfg.rate) if cfg.clock_hz else None
        tick = clock.publish if clock is not None else None
        period = 1.0 / cfg.clock_hz if cfg.clock_hz else 0.05
        _wait_for_subscribers(pubs, cfg.wait_subscribers_s)
        t_wall0 = time.monotonic()
        while True:
            stats["loops"] += 1
            start = time.monotonic()
            first = None
            for i, msg in enumerate(bag.messages(list(pubs))):
                if first is None:
                    first = msg.log_time_ns
                    if clock is not None:
                        clock.restart(first)
                offset = (msg.log_time_ns - first) / 1e9
                _sleep_until(start + offset / cfg.rate, tick, period)
                if clock is not None:  # the clock is never behind a message it announces
                    clock.publish(msg.log_time_ns)
                pubs[msg.topic].publish(msg.data)
                stats["published"] += 1
                if on_progress:
                    on_progress(i + 1, total, offset)
            if not cfg.loop or first is None:
                break
        _sleep_until(time.monotonic() + cfg.linger_s, tick, period)
        if clock is not None:
            stats["clock_messages"] = clock.published
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
