"""The pure runtime's relocalization requests and runtime tuning (no ROS): callers share the
running query, the next-frame and no-prior kinds, bounded waiting, settings from the next
query on."""

from __future__ import annotations

import dataclasses
import threading
import time

import pytest

from test_node_runtime import SlowPrior, frame_of, make, msg_of
from vlm_vpr_ros.priors import create_prior_provider
from vlm_vpr_ros.runtime.worker import QueryRuntime, RelocalizeKind, RuntimeConfig

# the first test also builds the demo map (25 s idle; over 60 s on the shared 2-core host at
# load 14)
pytestmark = pytest.mark.timeout(180)


def _wait_until(pred, timeout_s: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.02)
    return False


def test_callers_during_a_slow_prior_share_the_running_query(pipeline, image):
    prov = SlowPrior(1.5)
    rt, col = make(pipeline, prov, mode="on_trigger", max_frame_age_s=10.0)
    answers: list[tuple[bool, str]] = []

    def call():
        answers.append(rt.relocalize(20.0))
    try:
        rt.on_frame(frame_of(msg_of(image), 7_000_000_001))
        first = threading.Thread(target=call)
        first.start()
        assert _wait_until(lambda: len(prov.queries) == 1)  # the VLM call is running
        late = [threading.Thread(target=call) for _ in range(9)]
        for t in late:
            t.start()
        for t in [first, *late]:
            t.join(20.0)
    finally:
        rt.stop()
        prov.close()
    assert len(answers) == 10 and len(prov.queries) == 1 and len(col.outcomes) == 1
    assert all(ok for ok, _ in answers) and len({text for _, text in answers}) == 1
    assert answers[0][1].startswith("relocalized frame 7.000000001:")
    assert not any("busy" in text for _, text in answers)
    assert rt.stats.snapshot()["relocalize_requests"] == 10


def test_next_frame_request_waits_for_a_new_frame_and_never_joins(pipeline, image):
    prov = SlowPrior(1.0)
    rt, col = make(pipeline, prov, mode="on_trigger", max_frame_age_s=10.0)
    try:
        rt.on_frame(frame_of(msg_of(image), 1))
        latest = rt.request_relocalize()
        assert _wait_until(lambda: len(prov.queries) == 1)
        nxt = rt.request_relocalize(RelocalizeKind("next"))  # made during the running query
        assert latest.wait(20).frame.stamp_ns == 1
        assert nxt.wait(0.5) is None  # frame 1 predates the request: no answer from it
        rt.on_frame(frame_of(msg_of(image), 2))
        out = nxt.wait(20)
        assert out is not None and out.frame.stamp_ns == 2 and out.trigger == "relocalize"
    finally:
        rt.stop()
        prov.close()
    assert len(prov.queries) == 2


def test_no_prior_request_skips_the_provider(pipeline, image):
    prov = SlowPrior(30.0)
    rt, col = make(pipeline, prov, mode="on_trigger", max_frame_age_s=10.0)
    try:
        rt.on_frame(frame_of(msg_of(image), 3))
        t0 = time.monotonic()
        ok, text = rt.relocalize(20.0, kind=RelocalizeKind("latest", use_prior=False))
        took = time.monotonic() - t0
    finally:
        rt.stop()
        prov.close()
    assert ok and "no prior (not asked): global retrieval" in text, text
    assert prov.queries == [] and took < 15.0  # the 30 s prior was never asked for
    hyp = col.outcomes[0].hypothesis
    assert hyp.prior is None and "no_prior" in hyp.flags
    assert col.outcomes[0].timings_ms["prior_latency_ms"] == 0.0


def test_waiting_is_bounded_and_extra_callers_hear_it_is_scheduled(pipeline, image):
    col_outcomes = []
    rt = QueryRuntime(pipeline, create_prior_provider("none"), RuntimeConfig(mode="on_trigger"),
                      decode=lambda m: image, on_outcome=col_outcomes.append, max_waiters=1)
    rt.start()
    try:
        waiting = threading.Thread(target=rt.relocalize, args=(3.0,))
        waiting.start()  # no frame: it waits (the only waiter allowed)
        time.sleep(0.3)
        ok, text = rt.relocalize(3.0)
        assert not ok and "scheduled" in text and "shared" in text and "busy" not in text
        ok0, text0 = rt.relocalize(0.0)  # "do not wait": never success
        assert not ok0 and "scheduled (latest frame, with prior)" in text0
        assert "not waited for" in text0
        waiting.join(10.0)
    finally:
        rt.stop()


def test_settings_change_from_the_next_query_on(pipeline, image):
    rt, col = make(pipeline, create_prior_provider("fixed", {"lat": 39.6, "lon": 8.9}),
                   mode="on_trigger", max_frame_age_s=10.0)
    try:
        rt.on_frame(frame_of(msg_of(image), 11))
        first = rt.request_relocalize().wait(20)
        rt.update(localizer=dataclasses.replace(rt.localizer_config, top_p=7, rerank=False))
        second = rt.request_relocalize().wait(20)
        assert len(first.hypothesis.candidates) > 7 and len(second.hypothesis.candidates) == 7
        assert rt.pipeline.localizer.config.top_p == 7 and not rt.pipeline.localizer.config.rerank
        # on_trigger -> continuous at runtime: frames alone now start queries
        rt.update(RuntimeConfig(mode="continuous", min_period_s=0.0, max_frame_age_s=10.0))
        assert rt.stats.mode == "continuous"
        n = len(col.outcomes)
        rt.on_frame(frame_of(msg_of(image), 12))
        assert _wait_until(lambda: len(col.outcomes) > n)
        assert col.outcomes[-1].trigger == "continuous"
    finally:
        rt.stop()


def test_an_answer_nobody_waits_for_is_never_published(pipeline, image):
    """on_trigger: a caller that timed out before any frame came leaves nothing behind (the
    frames that come later start no query); one that gives up during the query (a slow prior)
    gets a timeout and the answer is not published (docs/node.md "Relocalize rules")."""
    prov = SlowPrior(2.0)
    rt, col = make(pipeline, prov, mode="on_trigger", max_frame_age_s=10.0)
    try:
        res = rt.relocalize_request(RelocalizeKind(), 0.5)
        assert res.code == "no_frame" and res.outcome is None
        ok, text = rt.relocalize(0.3)
        assert not ok and "[no_frame]" in text and "will not be published" in text
        rt.on_frame(frame_of(msg_of(image), 21))
        time.sleep(1.0)
        assert col.outcomes == [] and prov.queries == []  # nothing ran for them
        stages: list[str] = []
        res = rt.relocalize_request(RelocalizeKind(), 1.0, on_stage=stages.append)
        assert res.code == "timeout" and stages[:2] == ["waiting_for_frame", "asking_prior"]
        assert _wait_until(lambda: rt.stats.snapshot().get("relocalize_abandoned", 0) >= 1)
        time.sleep(2.5)
        assert col.outcomes == []  # the query finished, nobody waited: not published
        # a cancelled caller: the same
        flag = threading.Event()
        threading.Timer(0.3, flag.set).start()
        res = rt.relocalize_request(RelocalizeKind(), 30.0, cancelled=flag.is_set)
        assert res.code == "cancelled"
        time.sleep(3.0)
        assert col.outcomes == []
        # a caller that waits long enough gets it, published once, every stage seen
        stages = []
        res = rt.relocalize_request(RelocalizeKind(), 30.0, on_stage=stages.append)
        assert res.code == "answered" and len(col.outcomes) == 1
        assert col.outcomes[0] is res.outcome and res.outcome.trigger == "relocalize"
        assert stages == ["waiting_for_frame", "asking_prior", "retrieving", "verifying"]
    finally:
        rt.stop()
        prov.close()


def test_fire_and_forget_and_continuous_mode_keep_publishing(pipeline, image):
    """wait 0 (scheduled) is published; in continuous mode an abandoned relocalization goes
    out as a continuous answer (trigger continuous: no pose reset)."""
    prov = SlowPrior(1.0)
    rt, col = make(pipeline, prov, mode="on_trigger", max_frame_age_s=10.0)
    try:
        rt.on_frame(frame_of(msg_of(image), 31))
        assert rt.relocalize_request(RelocalizeKind(), 0.0).code == "scheduled"
        assert _wait_until(lambda: len(col.outcomes) == 1)
        assert col.outcomes[0].trigger == "relocalize"
        rt.update(RuntimeConfig(mode="continuous", min_period_s=1000.0, max_frame_age_s=10.0))
        rt.on_frame(frame_of(msg_of(image), 32))
        res = rt.relocalize_request(RelocalizeKind(), 0.3)
        assert res.code == "timeout"
        assert _wait_until(lambda: len(col.outcomes) == 2)
        assert col.outcomes[1].trigger == "continuous"
    finally:
        rt.stop()
        prov.close()


def test_a_caller_leaving_a_shared_request_is_told_only_what_is_true(pipeline, image):
    """Two callers share one request (slow prior); the short one times out while the other
    waits: it hears the answer may still be published for the other caller (not 'will not be
    published'), and the other gets it, published once. A caller that leaves alone still hears
    that it will not be published."""
    prov = SlowPrior(1.5)
    rt, col = make(pipeline, prov, mode="on_trigger", max_frame_age_s=10.0)
    try:
        rt.on_frame(frame_of(msg_of(image), 41))
        long_wait: list = []
        other = threading.Thread(target=lambda: long_wait.append(
            rt.relocalize_request(RelocalizeKind(), 30.0)))
        other.start()
        assert _wait_until(lambda: len(prov.queries) == 1)  # its query asks the slow prior
        ok, text = rt.relocalize(0.5)
        other.join(30.0)
        assert not ok and text.endswith("[timeout]") and "will not be published" not in text
        assert "may still be published on fix for them" in text
        assert long_wait[0].code == "answered" and col.outcomes == [long_wait[0].outcome]
        assert col.outcomes[0].trigger == "relocalize"
        rt.on_frame(frame_of(msg_of(image), 42))
        ok, text = rt.relocalize(0.5)  # alone: nobody else wants it
        assert not ok and "it will not be published as a relocalization [timeout]" in text
    finally:
        rt.stop()
        prov.close()
