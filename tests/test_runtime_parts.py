"""The node runtime's pure pieces (no ROS): the admission limit, the callers in progress, one
map reload at a time, the log level of each published outcome, waiting for the prior."""

from __future__ import annotations

import concurrent.futures as cf
import threading
import time
from types import SimpleNamespace

import pytest

from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.priors.provider import Prior, PriorQuery, PriorResult
from vlm_vpr_ros.runtime.admission import MAX_WAITERS, CallGate, WaiterLimit
from vlm_vpr_ros.runtime.map_reload import BUSY, MapReloader, reload_pipeline, reloaded_text
from vlm_vpr_ros.runtime.outcome import Frame, QueryOutcome
from vlm_vpr_ros.runtime.prior_wait import await_prior, request_prior
from vlm_vpr_ros.runtime.relocalize import outcome_log_line

pytestmark = pytest.mark.timeout(60)


def test_waiter_limit_admits_up_to_its_limit():
    limit = WaiterLimit(2)
    assert [limit.enter(), limit.enter(), limit.enter()] == [True, True, False]
    limit.leave()
    assert limit.enter() and not limit.enter()
    one = WaiterLimit(0)  # at least one caller may always wait
    assert one.enter() and not one.enter()
    default = WaiterLimit()
    assert sum(default.enter() for _ in range(MAX_WAITERS + 5)) == MAX_WAITERS


def test_call_gate_counts_callers_and_closes():
    gate = CallGate()
    assert gate.open and gate.enter() and gate.enter() and gate.in_progress == 2
    gate.close()
    assert not gate.open and not gate.enter()  # closing: answered at once, not counted
    assert gate.enter(force=True) and gate.in_progress == 3  # an accepted goal still counts
    assert not gate.wait_idle(0.05)
    leavers = [threading.Timer(0.05 * (i + 1), gate.leave) for i in range(3)]
    for t in leavers:
        t.start()
    assert gate.wait_idle(30.0) and gate.in_progress == 0
    gate.reopen()
    assert gate.open and gate.enter()


def _pipe(n_refs: int, generation: int, reloaded=None):
    m = SimpleNamespace(n_references=n_refs, submaps=[0, 1], path="/maps/m",
                        manifest={"generation": generation})
    return SimpleNamespace(map=m, reloaded=reloaded)


def test_map_reloader_inactive_paths():
    new = _pipe(12, 2)
    old = _pipe(10, 1, reloaded=lambda: new)
    reloader = MapReloader()
    ok, text, keep = reloader.reload(None, old, "~/m")
    assert ok and keep is new and text == ("map ~/m reloaded: 12 references (used from the "
                                           "next activate)")
    ok, text, keep = reloader.reload(None, None, "~/m")
    assert not ok and keep is None and text == ("map reload failed: no map loaded: configure "
                                                "first")  # None: the node keeps what it has

    def broken():
        raise MapError("manifest.json is truncated")
    bad = _pipe(10, 1, reloaded=broken)
    ok, text, keep = reloader.reload(None, bad, "~/m")
    assert not ok and keep is None and "manifest.json is truncated" in text
    assert reload_pipeline(bad) == (None, "manifest.json is truncated")
    assert reloaded_text(old, new, 1.5) == ("map /maps/m reloaded in 1.5 s: 10 -> 12 "
                                             "references, 2 -> 2 submaps (generation 1 -> 2)")


def test_map_reloader_answers_a_second_caller_busy_at_once():
    """While one reload runs, another caller is answered BUSY without waiting for it; the
    active runtime's pipeline (swapped by it) is what the node keeps."""
    entered, release = threading.Event(), threading.Event()
    swapped = _pipe(5, 3)

    class Runtime:
        pipeline = _pipe(4, 2)

        def reload_map(self):
            entered.set()
            assert release.wait(30.0)
            self.pipeline = swapped
            return True, "reloaded"

    reloader, runtime, answers = MapReloader(), Runtime(), []
    first = threading.Thread(target=lambda: answers.append(
        reloader.reload(runtime, runtime.pipeline, "m")))
    first.start()
    assert entered.wait(30.0)
    loaded = runtime.pipeline
    assert reloader.reload(runtime, loaded, "m") == (False, BUSY, None)  # keeps its own
    release.set()
    first.join(30.0)
    assert answers == [(True, "reloaded", swapped)]
    # free again once the first reload answered
    release.set()
    assert reloader.reload(runtime, swapped, "m") == (True, "reloaded", swapped)


def test_outcome_log_line_without_a_fix():
    frame = Frame(None, 7_000_000_001, "cam")
    failed = QueryOutcome(frame, "continuous", error="localization failed: bad map")
    assert outcome_log_line(failed) == (
        "error", "no fix for frame 7.000000001: localization failed: bad map")
    # undecodable frames: counted and logged throttled by the runtime, not per frame
    assert outcome_log_line(QueryOutcome(frame, "continuous",
                                         error="undecodable frame: bad encoding")) is None


def test_prior_wait_turns_every_failure_into_a_failed_prior():
    class Raising:
        name = "raising"

        def request(self, query):
            raise RuntimeError("socket exploded")

    fut = request_prior(Raising(), PriorQuery(image=None, encoded=None, key="1.0"))
    res = await_prior("raising", fut, time.monotonic(), 30.0, lambda: False)
    assert res.prior is None and res.reason == "error: socket exploded"
    wrong: cf.Future = cf.Future()
    wrong.set_result("lat 1, lon 2")  # not a PriorResult
    res = await_prior("p", wrong, time.monotonic(), 30.0, lambda: False)
    assert res.prior is None and res.reason == "error: provider returned str"
    never: cf.Future = cf.Future()
    res = await_prior("p", never, time.monotonic(), 30.0, lambda: True)
    assert res.reason == "shutdown" and never.cancelled()
    never = cf.Future()
    res = await_prior("p", never, time.monotonic() - 31.0, 30.0, lambda: False)
    assert res.reason == "timeout" and never.cancelled()
    ok: cf.Future = cf.Future()
    good = PriorResult(Prior(1.0, 2.0, "p"), "p")
    ok.set_result(good)
    assert await_prior("p", ok, time.monotonic(), 30.0, lambda: False) is good
