"""The node's pure runtime (no ROS): slot, worker, async prior with timeout, relocalize."""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from msg_adapters.image import message_to_rgb
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.priors import create_prior_provider
from vlm_vpr_ros.priors.provider import Prior, PriorProvider, PriorQuery, PriorResult
from vlm_vpr_ros.runtime.relocalize import outcome_log_line
from vlm_vpr_ros.runtime.worker import Frame, QueryRuntime, RuntimeConfig, outcome_summary

pytestmark = pytest.mark.timeout(60)
QUERY = "546314506564628.jpg"  # Sanluri, Sardinia
TRUTH = (39.55910238557, 8.8888751944543)


class SlowPrior(PriorProvider):
    """A provider that answers after ``delay_s`` on its own thread (the async contract)."""

    name = "slow"

    def __init__(self, delay_s: float, lat: float = TRUTH[0] + 0.05, lon: float = TRUTH[1]):
        self.delay_s, self.prior = delay_s, Prior(lat, lon, "slow")
        self.pool = cf.ThreadPoolExecutor(1)
        self.queries: list[PriorQuery] = []
        self.closed = threading.Event()

    def request(self, query):
        self.queries.append(query)
        return self.pool.submit(self._answer)

    def _answer(self):
        if self.closed.wait(self.delay_s):  # close() ends the wait (no thread left sleeping)
            return PriorResult.failure("slow", "cancelled")
        return PriorResult(self.prior, "slow", latency_s=self.delay_s)

    def close(self):
        self.closed.set()
        self.pool.shutdown(wait=False, cancel_futures=True)


class BrokenPrior(PriorProvider):
    name = "broken"

    def request(self, query):
        raise RuntimeError("socket exploded")


def msg_of(rgb: np.ndarray, stamp_ns: int = 1_000_000_123, encoding: str = "rgb8"):
    h, w = rgb.shape[:2]
    return SimpleNamespace(height=h, width=w, encoding=encoding, is_bigendian=0, step=w * 3,
                           data=rgb.tobytes())


def frame_of(msg, stamp_ns=1_000_000_123) -> Frame:
    return Frame(msg, stamp_ns, "cam")


class Collector:
    def __init__(self):
        self.outcomes, self.cond = [], threading.Condition()

    def __call__(self, out):
        with self.cond:
            self.outcomes.append(out)
            self.cond.notify_all()

    def wait(self, n: int, timeout: float = 20.0):
        with self.cond:
            assert self.cond.wait_for(lambda: len(self.outcomes) >= n, timeout), \
                f"only {len(self.outcomes)} of {n} outcomes"
            return self.outcomes[n - 1]


def make(pipeline, provider, **cfg):
    col = Collector()
    rt = QueryRuntime(pipeline, provider, RuntimeConfig(**cfg), decode=message_to_rgb,
                      on_outcome=col)
    rt.start()
    return rt, col


def test_fix_near_truth_with_fixed_prior(pipeline, image):
    rt, col = make(pipeline, create_prior_provider("fixed", {"lat": 39.6, "lon": 8.9}),
                   min_period_s=0.0)
    try:
        rt.on_frame(frame_of(msg_of(image), 42_000_000_007))
        out = col.wait(1)
    finally:
        rt.stop()
    h = out.hypothesis
    assert out.error == "" and out.trigger == "continuous" and out.frame.stamp_ns == 42_000_000_007
    assert haversine_km(h.lat, h.lon, *TRUTH) < 1.0 and not h.flagged
    assert {"decode_ms", "descriptor_ms", "prior_wait_ms", "retrieval_ms", "rerank_ms",
            "query_ms"} <= set(out.timings_ms)
    snap = rt.stats.snapshot()
    assert (snap["frames_received"], snap["frames_processed"], snap["fixes"]) == (1, 1, 1)
    level, message, values = rt.stats.report()
    assert level == "OK" and "prior fixed" in message and values["candidates"] >= 1
    ok, text = outcome_summary(out, 0.0)
    assert ok and "lat 39.559" in text and "prior fixed" in text
    # a continuous-mode fix is not a relocalization: the log line says what it is
    assert text.startswith("fix for frame 42.000000007:") and "relocalized" not in text
    # the node's log line: debug for a continuous fix, info for a relocalization, warning when
    # flagged (throttled by the node)
    assert outcome_log_line(out) == ("debug", text)
    out.trigger = "relocalize"
    assert outcome_summary(out, 0.0)[1].startswith("relocalized frame 42.000000007:")
    assert outcome_log_line(out) == ("info", outcome_summary(out, 0.0)[1])
    out.hypothesis = dataclasses.replace(h, flags=("no_prior",))
    assert out.hypothesis.flagged
    assert outcome_log_line(out) == ("warning", outcome_summary(out, 0.0)[1])


def test_fallback_fix_says_the_same_everywhere(pipeline, image):
    """fallback_status: fix publishes an answer failing the status rule as STATUS_FIX with a
    least sigma: the relocalize answer and diagnostics say that status and that sigma too
    (and diagnostics WARN: it is not a precise fix)."""
    from msg_adapters.navsat import STATUS_FIX, FixPolicy, fix_fields
    from vlm_vpr_ros.localization.verification.status import StatusPolicy, stamp_status

    policy = StatusPolicy(fix_max_sigma_m=0.001, fallback_status="fix",
                          fallback_min_sigma_m=5000.0)
    pipeline.tune(policy, None)
    rt, col = make(pipeline, create_prior_provider("none", {}), min_period_s=0.0)
    try:
        rt.on_frame(frame_of(msg_of(image), 43_000_000_000))
        out = col.wait(1)
    finally:
        rt.stop()
        pipeline.tune(StatusPolicy(), None)
    h = out.hypothesis
    f = fix_fields(h, FixPolicy(status=policy))
    assert f.status == STATUS_FIX and not f.precise and f.sigma_m >= 5000.0 - 1e-6
    ok, text = outcome_summary(out, 0.0)
    # reported, but no success: a robot must not act on it as on a precise fix
    assert not ok and "STATUS_FIX (fallback: " in text and f"sigma {f.sigma_m:.0f} m" in text
    level, message, values = rt.stats.report()
    assert level == "WARN" and message.startswith("no precise fix: STATUS_FIX (fallback")
    assert values["status"] == "STATUS_FIX" and abs(values["last_sigma_m"] - f.sigma_m) < 1e-6
    # the fix goes out as STATUS_FIX, but no pose: a fallback fix is no place to reset an EKF
    sent = published_by_outputs(out, FixPolicy(status=policy))
    assert [kind for kind, _ in sent] == ["fix"] and sent[0][1].status.status == STATUS_FIX
    # under the default fallback (no_fix) it is NO_FIX: no pose, and no success either
    out.hypothesis = stamp_status(dataclasses.replace(h, status="", status_reason=""),
                                  StatusPolicy(fix_max_sigma_m=0.001))
    ok, text = outcome_summary(out, 0.0)
    assert not ok and "NO_FIX (sigma" in text
    assert published_by_outputs(out, FixPolicy())[0][1].status.status != STATUS_FIX
    assert [kind for kind, _ in published_by_outputs(out, FixPolicy())] == ["fix"]
    # the same answer stamped by a rule it passes (a precise fix) gets its pose
    again = dataclasses.replace(h, status="", status_reason="", p_correct=0.99,
                                protection_m=30.0)
    out.hypothesis = stamp_status(again, StatusPolicy(fix_max_sigma_m=1e7))
    assert out.hypothesis.status == "fix"
    ok, text = outcome_summary(out, 0.0)
    assert ok and "STATUS_FIX, sigma" in text  # the relocalize service's success
    sent = published_by_outputs(out, FixPolicy())
    assert [kind for kind, _ in sent] == ["fix", "pose"]
    assert sent[1][1].pose.covariance[0] == pytest.approx(sent[0][1].position_covariance[0])


def published_by_outputs(out, policy) -> list[tuple[str, object]]:
    """What ``Outputs.publish`` sends for ``out`` (pose_on every_fix, a local ENU frame), on
    recording publishers instead of a ROS node."""
    from vlm_vpr_ros.ros.publishers import Outputs
    from vlm_vpr_ros.runtime.metric_frame import metric_frame
    from vlm_vpr_ros.runtime.stats import Throttle

    sent: list[tuple[str, object]] = []

    def publisher(kind):
        return SimpleNamespace(publish=lambda msg: sent.append((kind, msg)))

    frame = metric_frame("local_enu", "map", datum_lat=TRUTH[0], datum_lon=TRUTH[1])
    outputs = SimpleNamespace(fix=publisher("fix"), pose=publisher("pose"), frame=frame,
                              _pose_log=Throttle(10.0), _pose_kept=False,
                              _latched=False)
    cfg = SimpleNamespace(frame_id="gps", pose_on="every_fix", publish_debug=False)
    Outputs.publish(outputs, out, cfg, policy)
    return sent


class FakeClock:
    """A manual clock (seconds), like a node's clock under use_sim_time."""

    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_min_period_and_frame_age_follow_the_given_clock(pipeline, image):
    """min_period_s counts on the runtime's clock (the node passes its ROS clock, so sim time
    applies), not on wall time; a clock that jumps back does not stall the queries."""
    clock = FakeClock()
    col = Collector()
    rt = QueryRuntime(pipeline, create_prior_provider("none", {}),
                      RuntimeConfig(min_period_s=10.0, max_frame_age_s=5.0),
                      decode=message_to_rgb, on_outcome=col, clock=clock)
    rt.start()
    try:
        rt.on_frame(frame_of(msg_of(image), 1))
        col.wait(1)  # the first query starts at once
        assert rt._last_start == 100.0
        rt.on_frame(frame_of(msg_of(image), 2))
        time.sleep(0.6)  # wall time passes, the clock does not: no second query
        assert len(col.outcomes) == 1
        clock.t = 109.0
        time.sleep(0.4)
        assert len(col.outcomes) == 1
        clock.t = 110.5  # 10 s of clock time since the first start
        assert col.wait(2).frame.stamp_ns == 2
        rt.on_frame(frame_of(msg_of(image), 3))
        clock.t = 50.0  # a looped bag: time jumps back; the period restarts at once
        assert col.wait(3).frame.stamp_ns == 3
        # frame age on the clock: a frame received at t=50 is stale at t=56 for relocalize
        rt.on_frame(frame_of(msg_of(image), 4))
        assert rt._slot is not None and rt._slot.received == 50.0
    finally:
        rt.stop()


def test_slow_prior_does_not_block_intake(pipeline, image):
    prov = SlowPrior(1.0)
    rt, col = make(pipeline, prov, min_period_s=0.0, prior_timeout_s=10.0)
    try:
        rt.on_frame(frame_of(msg_of(image), 1))
        while not prov.queries:  # the worker took the frame and asked for the prior
            time.sleep(0.01)
        for i in range(300):  # intake keeps working while the prior is pending
            rt.on_frame(frame_of(msg_of(image), 2 + i))
        pending = rt.busy and len(col.outcomes) == 0
        out = col.wait(1)
    finally:
        rt.stop()
    assert pending  # all 300 frames were taken while the first query waited for the VLM
    snap = rt.stats.snapshot()
    assert snap["frames_received"] == 301
    assert snap["frames_dropped"] >= 299 - snap["frames_processed"]  # one slot, by design
    assert out.frame.stamp_ns == 1 and out.hypothesis.prior.source == "slow"
    assert prov.queries[0].key == "0.000000001" and prov.queries[0].image.shape == image.shape


def test_prior_timeout_gives_flagged_global_fix(pipeline, image):
    prov = SlowPrior(30.0)
    rt, col = make(pipeline, prov, min_period_s=0.0, prior_timeout_s=0.3)
    try:
        rt.on_frame(frame_of(msg_of(image)))
        out = col.wait(1)
        level, message, _ = rt.stats.report()
    finally:
        rt.stop()
    h = out.hypothesis
    assert h.flagged and {"no_prior", "prior_failed", "global"} <= set(h.flags)
    assert h.prior_result.reason == "timeout" and h.prior is None
    assert haversine_km(h.lat, h.lon, *TRUTH) < 1.0  # global retrieval still finds it here
    assert level == "WARN" and "flagged" in message and "timeout" in message


def test_provider_exception_is_a_flagged_fix(pipeline, image):
    rt, col = make(pipeline, BrokenPrior(), min_period_s=0.0)
    try:
        rt.on_frame(frame_of(msg_of(image)))
        out = col.wait(1)
    finally:
        rt.stop()
    assert out.hypothesis.flagged and "socket exploded" in out.hypothesis.prior_result.reason


def test_undecodable_frame_is_skipped_and_counted(pipeline, image):
    rt, col = make(pipeline, create_prior_provider("none"), min_period_s=0.0)
    try:
        rt.on_frame(frame_of(msg_of(image, encoding="yuv444_unknown")))
        bad = col.wait(1)
        level, message, _ = rt.stats.report()
        rt.on_frame(frame_of(msg_of(image)))
        good = col.wait(2)
    finally:
        rt.stop()
    assert bad.hypothesis is None and bad.error.startswith("undecodable frame")
    assert level == "WARN" and "undecodable" in message
    assert good.hypothesis is not None
    snap = rt.stats.snapshot()
    assert snap["decode_errors"] == 1 and snap["fixes"] == 1 and snap["query_errors"] == 0


def test_unexpected_failure_is_an_error_and_the_worker_survives(pipeline, image):
    col = Collector()

    def decode(msg):
        if getattr(msg, "explode", False):
            raise RuntimeError("bug in a decoder")
        return message_to_rgb(msg)

    rt = QueryRuntime(pipeline, create_prior_provider("none"), RuntimeConfig(min_period_s=0.0),
                      decode=decode, on_outcome=col)
    rt.start()
    try:
        bad = msg_of(image)
        bad.explode = True
        rt.on_frame(frame_of(bad))
        first = col.wait(1)
        level, message, _ = rt.stats.report()
        rt.on_frame(frame_of(msg_of(image)))
        second = col.wait(2)
    finally:
        rt.stop()
    assert "RuntimeError: bug in a decoder" in first.error
    assert level == "ERROR" and "bug in a decoder" in message
    assert second.hypothesis is not None


def test_rate_limit_in_continuous_mode(pipeline, image):
    rt, col = make(pipeline, create_prior_provider("none"), min_period_s=0.4)
    msg = msg_of(image)
    try:
        t_end = time.monotonic() + 1.5
        i = 0
        while time.monotonic() < t_end:
            rt.on_frame(frame_of(msg, i))
            i += 1
            time.sleep(0.01)
    finally:
        rt.stop()
    n = len(col.outcomes)
    assert 1 <= n <= 1.5 / 0.4 + 1
    starts = [o.started for o in col.outcomes]
    assert all(b - a >= 0.4 - 1e-3 for a, b in zip(starts, starts[1:]))


def test_on_trigger_mode_queries_only_when_asked(pipeline, image):
    rt, col = make(pipeline, create_prior_provider("none"), mode="on_trigger",
                   max_frame_age_s=5.0)
    try:
        ticket = rt.request_relocalize()  # no frame yet: scheduled, answered later
        assert ticket.wait(0.3) is None
        ok, text = outcome_summary(None, 0.3)
        assert not ok and "scheduled" in text
        rt.on_frame(frame_of(msg_of(image), 5))
        out = ticket.wait(20)
        assert out is not None and out.trigger == "relocalize" and out.frame.stamp_ns == 5
        for i in range(20):  # frames alone never start a query in on_trigger mode
            rt.on_frame(frame_of(msg_of(image), 10 + i))
        time.sleep(0.5)
        assert len(col.outcomes) == 1
        again = rt.request_relocalize().wait(20)  # the latest fresh frame is used at once
        assert again.frame.stamp_ns == 29
    finally:
        rt.stop()
    assert rt.stats.snapshot()["relocalize_requests"] == 2


def test_stop_interrupts_a_hung_prior(pipeline, image):
    prov = SlowPrior(120.0)
    rt, col = make(pipeline, prov, min_period_s=0.0, prior_timeout_s=120.0)
    rt.on_frame(frame_of(msg_of(image)))
    while not prov.queries:
        time.sleep(0.01)
    rt.stop(timeout_s=10.0)
    assert not rt._thread.is_alive()
    assert col.outcomes == []  # a query cut short by shutdown publishes nothing


def test_runtime_config_rejects_bad_values():
    from vlm_vpr_ros.errors import ConfigError

    with pytest.raises(ConfigError, match="choices: continuous, on_trigger"):
        RuntimeConfig(mode="sometimes")
    with pytest.raises(ConfigError):
        RuntimeConfig(prior_timeout_s=0)


def test_diagnostics_warn_when_the_camera_goes_silent(monkeypatch):
    from vlm_vpr_ros.runtime import stats as runtime_stats

    monkeypatch.setattr(runtime_stats, "NO_FRAMES_WARN_S", 0.2)
    stats = runtime_stats.RuntimeStats("none", "continuous")
    assert stats.report()[0] == "OK"  # just started: waiting is fine
    time.sleep(0.3)
    assert stats.report()[:2] == ("WARN", "no images received")
    stats.frame_received(False)
    assert stats.report()[0] == "OK"
    time.sleep(0.3)
    level, message, values = stats.report()
    assert level == "WARN" and message.startswith("no images for")
    assert values["last_frame_age_s"] >= 0.3
    trig = runtime_stats.RuntimeStats("none", "on_trigger")
    time.sleep(0.3)
    assert trig.report()[:2] == ("OK", "waiting for a relocalize request")
