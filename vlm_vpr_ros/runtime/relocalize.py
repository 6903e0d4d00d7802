"""Relocalization requests of the node's runtime (pure, no ROS).

A request names a *kind* (:class:`RelocalizeKind`): which frame to use and whether to ask the
prior provider. Concurrent requests of one kind share one query (:class:`RelocalizeTicket`);
every caller waits for that shared outcome, bounded by its own wait time. The node offers one
``std_srvs/Trigger`` service per kind (docs/node.md "Services": the compatibility path) and
the typed ``vlm_vpr_interfaces`` service and action (:mod:`vlm_vpr_ros.runtime.answer`).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.localization.verification.status import horizontal_sigma, is_precise_fix

FRAME_POLICIES = ("latest", "next")


@dataclass(frozen=True)
class RelocalizeKind:
    """What a relocalize caller asks for.

    ``frame``: ``latest`` uses the newest frame if it was received at most ``max_frame_age_s``
    ago, else the next one; ``next`` uses the first frame received after the request (the
    camera was covered, the robot was just carried somewhere). ``use_prior``: False skips the
    prior provider (global retrieval, flagged ``no_prior``): no VLM call and no VLM latency.
    """

    frame: str = "latest"
    use_prior: bool = True

    def __post_init__(self) -> None:
        if self.frame not in FRAME_POLICIES:
            raise ConfigError(f"unknown relocalize frame policy {self.frame!r}; choices: "
                              f"{', '.join(FRAME_POLICIES)}")

    @property
    def label(self) -> str:
        return f"{self.frame} frame, {'with' if self.use_prior else 'without'} prior"


#: the stages of a relocalization, in order (the action's feedback)
STAGES = ("waiting_for_frame", "asking_prior", "retrieving", "verifying")


class RelocalizeTicket:
    """A pending relocalization of one kind; its callers wait for the shared outcome.

    Who is still interested (docs/node.md "Relocalize rules"): callers that wait
    (:meth:`attach` ... :meth:`leave`) and *detached* requests (``wait 0``, or
    :meth:`QueryRuntime.request_relocalize` directly: fire and forget, the answer goes out on
    the topics). A ticket whose every waiter gave up (timed out, cancelled) and that no
    detached request holds is *abandoned*: its answer is never published as a relocalization
    (no pose reset). :meth:`claim` (the worker, before publishing) and :meth:`leave` (a
    caller giving up) are decided under one lock, so a caller that gets a timeout never sees
    its pose published afterwards, and a published pose always reaches its waiting callers.
    """

    def __init__(self, kind: RelocalizeKind, after_seq: int) -> None:
        self.kind = kind
        self.after_seq = after_seq  # frames numbered above this arrived after the request
        self.requested = time.monotonic()
        self._done = threading.Event()
        self._lock = threading.Condition()
        self.outcome: Any = None  # the worker's QueryOutcome
        self.waiters = 0
        self.detached = False
        self.gave_up = 0  # callers that left without an answer
        self.claimed = False  # the worker is publishing the answer: callers get it
        self.stages: list[str] = ["waiting_for_frame"]

    def attach(self) -> None:
        with self._lock:
            self.waiters += 1

    def detach(self) -> None:
        """A request nobody waits for (wait 0): its answer is still published."""
        with self._lock:
            self.detached = True

    def leave(self) -> bool:
        """A waiting caller gives up (timeout or cancel): True when it must be told so (the
        answer was not claimed for publishing); False when the answer is being published and
        the caller gets it (wait on, briefly)."""
        with self._lock:
            if self.claimed or self._done.is_set():
                return False
            self.waiters -= 1
            self.gave_up += 1
            return True

    @property
    def wanted(self) -> bool:
        """Someone still wants the answer: a caller waits, or a detached request holds it."""
        with self._lock:
            return self.waiters > 0 or self.detached

    @property
    def abandoned(self) -> bool:
        with self._lock:
            return self.waiters <= 0 and not self.detached and self.gave_up > 0

    def claim(self) -> bool:
        """The worker is about to publish this ticket's answer: True if someone still wants
        it (then callers can no longer leave), False when abandoned."""
        with self._lock:
            if self.waiters <= 0 and not self.detached and self.gave_up > 0:
                return False
            self.claimed = True
            return True

    def stage(self, name: str) -> None:
        """The query answering this ticket reached stage ``name`` (:data:`STAGES`)."""
        with self._lock:
            if self.stages[-1] != name:
                self.stages.append(name)
                self._lock.notify_all()

    def wait_stage(self, seen: int, timeout_s: float) -> list[str]:
        """Block until there are more than ``seen`` stages, the answer, or the timeout."""
        with self._lock:
            self._lock.wait_for(lambda: len(self.stages) > seen or self._done.is_set(),
                                max(0.0, timeout_s))
            return list(self.stages)

    def accepts(self, frame: Any, now: float, max_age_s: float) -> bool:
        """Whether ``frame`` (the worker's Frame, or None) may answer this request at time
        ``now`` (the runtime's clock)."""
        if frame is None:
            return False
        if self.kind.frame == "next":
            return frame.seq > self.after_seq
        return now - frame.received <= max_age_s

    def finish(self, outcome: Any) -> None:
        with self._lock:
            self.outcome = outcome
            self._done.set()
            self._lock.notify_all()

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def wait(self, timeout_s: float) -> Any:
        self._done.wait(max(0.0, timeout_s))
        return self.outcome


@dataclass
class RelocalizeResult:
    """What one relocalize caller gets: ``code`` (:data:`OUTCOMES`), the shared outcome (the
    worker's QueryOutcome; None unless answered/failed), the seconds waited and the stages the
    query went through. ``shared``: the caller gave up (timeout, cancel) while others still
    wanted the answer, so it may still be published for them (never for this caller)."""

    code: str
    outcome: Any = None
    waited_s: float = 0.0
    stages: tuple[str, ...] = ()
    shared: bool = False


#: what happened to a relocalize request (vlm_vpr_interfaces/Answer OUTCOME_*)
OUTCOMES = ("answered", "failed", "no_frame", "timeout", "not_active", "scheduled",
            "cancelled", "busy", "rejected")


def await_answer(ticket: RelocalizeTicket, wait_s: float,
                 cancelled: Callable[[], bool] | None = None,
                 on_stage: Callable[[str], None] | None = None,
                 give_up: Callable[[RelocalizeTicket], None] | None = None) -> RelocalizeResult:
    """Wait (as an attached caller of ``ticket``) at most ``wait_s`` for the shared answer,
    reporting each new stage to ``on_stage``; ``cancelled()`` true ends the wait early. A caller
    that gives up leaves the ticket (``give_up(ticket)`` then lets the runtime drop it when it
    is abandoned), unless the answer is already being published: then it waits for it."""
    t0 = time.monotonic()
    deadline = t0 + wait_s
    seen = 0
    code = ""
    while not ticket.done:
        stages = ticket.wait_stage(seen, min(0.05, max(0.0, deadline - time.monotonic())))
        if on_stage is not None:
            for name in stages[seen:]:
                on_stage(name)
        seen = len(stages)
        if ticket.done:
            break
        if cancelled is not None and cancelled():
            code = "cancelled"
        elif time.monotonic() >= deadline:
            code = "no_frame" if seen <= 1 else "timeout"
        else:
            continue
        if ticket.leave():
            shared = ticket.wanted  # another caller (or a wait-0 request) still holds it
            if give_up is not None:
                give_up(ticket)
            return RelocalizeResult(code, None, time.monotonic() - t0, tuple(ticket.stages),
                                    shared)
        ticket.wait(60.0)  # claimed: being published right now
        break
    out = ticket.outcome
    waited = time.monotonic() - t0
    if out is None:  # the runtime stopped (deactivate, shutdown) before answering
        return RelocalizeResult("not_active", None, waited, tuple(ticket.stages))
    return RelocalizeResult("answered" if out.hypothesis is not None else "failed", out, waited,
                            tuple(ticket.stages))


def no_answer_text(res: RelocalizeResult, fix_topic: str = "fix", label: str = "") -> str:
    """The sentence for a caller that got no outcome (``res.code`` other than answered /
    failed), ending with the code in brackets. A caller that gave up is told only what is true
    for it: with others still waiting (``res.shared``) the answer may still be published for
    them, so "it will not be published" is said only when nobody else wants it."""
    what, kind = "relocalization", f" ({label})" if label else ""
    if res.shared:
        fate = (f"other callers still wait for it, so it may still be published on {fix_topic} "
                "for them (not as an answer to this call)")
    else:
        fate = "it will not be published as a relocalization"
    text = {
        "scheduled": (f"{what} scheduled{kind} (not waited for: relocalize_wait_s 0); the fix "
                      f"will be published on {fix_topic}"),
        "busy": (f"{what} scheduled{kind}, shared with the callers already waiting for it; the "
                 f"fix will be published on {fix_topic}"),
        "no_frame": (f"{what} gave no result within {res.waited_s:.1f} s: no usable frame "
                     "arrived (camera silent?); "
                     + (fate if res.shared else "the request is dropped, it will not be "
                        "published")),
        "timeout": (f"{what} gave no result within {res.waited_s:.1f} s (stages: "
                    f"{', '.join(res.stages)}); {fate}"),
        "cancelled": f"{what} cancelled; {fate}",
        "not_active": "the node is not active (or stopped localizing): activate it first",
    }.get(res.code, f"{what}: {res.code}")
    return text if res.code in ("scheduled", "busy") else f"{text} [{res.code}]"


def outcome_summary(outcome: Any, waited_s: float,
                    fix_topic: str = "fix") -> tuple[bool, str]:
    """(success, human-readable sentence) answering a relocalize request (``outcome``: the
    worker's QueryOutcome, None when none came in time). ``success`` means the robot may act
    on the answer: a STATUS_FIX that passed the status rule (the answers that also go out on
    ``pose``); a NO_FIX or a ``fallback_status: fix`` answer is reported, with success false."""
    if outcome is None:
        return False, (f"relocalization scheduled, no result within {waited_s:.1f} s (waiting "
                       f"for a frame or for the prior); the fix will be published on "
                       f"{fix_topic}")
    frame = outcome.frame
    if outcome.hypothesis is None:
        return False, f"relocalization on frame {frame.key} gave no fix: {outcome.error}"
    h = outcome.hypothesis
    pr = h.prior_result
    if h.prior is not None:
        prior = f"prior {h.prior.source} ({h.prior.lat:.4f}, {h.prior.lon:.4f})"
    else:
        prior = f"no prior ({pr.reason if pr else 'not asked'}): global retrieval"
    flag = f" FLAGGED [{'|'.join(h.flags)}]" if h.flagged else ""
    # the status and sigma of the published fix (docs/verification.md)
    status = ((f"STATUS_FIX ({h.status_reason})" if h.status_reason else "STATUS_FIX")
              if h.status == "fix" else f"NO_FIX ({h.status_reason or 'unverified'})")
    p = "" if math.isnan(h.p_correct) else f"p_correct {h.p_correct:.3f}, "
    if math.isfinite(h.protection_m):  # integrity: the error bound at risk 1e-3
        p = f"protection {h.protection_m:.0f} m, {p}"
    took = outcome.finished - outcome.started
    what = "relocalized frame" if outcome.trigger == "relocalize" else "fix for frame"
    return is_precise_fix(h), (f"{what} {frame.key}: lat {h.lat:.6f}, lon {h.lon:.6f}, "
                               f"{status}, sigma {horizontal_sigma(h):.0f} m, {p}reference "
                               f"{h.ref_id}, submap {h.submap}, {prior}, "
                               f"{len(h.candidates)} candidates, {took:.2f} s{flag}")
