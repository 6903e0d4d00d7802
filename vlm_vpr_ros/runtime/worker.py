"""The query logic of the ROS node, without ROS: latest-frame slot, worker, statistics.

Threads: the image callback only calls :meth:`QueryRuntime.on_frame`, which stores the still
undecoded message in a one-frame slot (a newer frame replaces an unused one: *dropped by design*,
counted). One worker thread takes frames when a query is due — every ``min_period_s`` in
``continuous`` mode, on :meth:`QueryRuntime.request_relocalize` in both modes — decodes the
frame, starts the prior request (asynchronous, see :mod:`vlm_vpr_ros.priors.base`), computes the
descriptor meanwhile, waits for the prior at most ``prior_timeout_s``, localizes (flagged global
retrieval when the prior failed) and hands a :class:`QueryOutcome` to ``on_outcome``. Nothing
here queues more than one frame and one relocalization request.

Time: ``min_period_s`` and frame ages (``max_frame_age_s``) are measured on the ``clock`` given
to :class:`QueryRuntime` (the node passes its ROS clock, so they follow ``/clock`` under
``use_sim_time``; default: ``time.monotonic``). A clock that jumps backwards (a bag replayed in
a loop) restarts the period instead of stalling the queries.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from vlm_vpr_ros.errors import ConfigError, ImageDecodeError, VlmVprError
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
from vlm_vpr_ros.priors.base import PriorProvider, PriorQuery, PriorResult
from vlm_vpr_ros.runtime.stats import RuntimeStats, Throttle
from vlm_vpr_ros.types import Hypothesis

log = logging.getLogger(__name__)
MODES = ("continuous", "on_trigger")


@dataclass(frozen=True)
class RuntimeConfig:
    mode: str = "continuous"
    min_period_s: float = 1.0
    prior_timeout_s: float = 30.0
    max_frame_age_s: float = 2.0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"unknown mode {self.mode!r}; choices: {', '.join(MODES)}")
        if not (self.min_period_s >= 0 and self.prior_timeout_s > 0
                and self.max_frame_age_s > 0):
            raise ConfigError("min_period_s must be >= 0; prior_timeout_s and "
                              "max_frame_age_s must be > 0")


@dataclass
class Frame:
    """A received, not yet decoded image message."""

    msg: Any
    stamp_ns: int
    frame_id: str
    received: float = field(default_factory=time.monotonic)

    @property
    def key(self) -> str:
        """Lookup key handed to the prior provider: the stamp as ``sec.nanosec``."""
        return f"{self.stamp_ns // 1_000_000_000}.{self.stamp_ns % 1_000_000_000:09d}"


@dataclass
class QueryOutcome:
    frame: Frame
    trigger: str  # "continuous" or "relocalize"
    hypothesis: Hypothesis | None = None
    error: str = ""  # why there is no hypothesis
    started: float = 0.0
    finished: float = 0.0
    timings_ms: dict[str, float] = field(default_factory=dict)


class RelocalizeTicket:
    """A pending relocalization; callers may wait for its outcome (bounded)."""

    def __init__(self) -> None:
        self.requested = time.monotonic()
        self._done = threading.Event()
        self.outcome: QueryOutcome | None = None

    def finish(self, outcome: QueryOutcome | None) -> None:
        self.outcome = outcome
        self._done.set()

    def wait(self, timeout_s: float) -> QueryOutcome | None:
        self._done.wait(max(0.0, timeout_s))
        return self.outcome


class QueryRuntime:
    """Owns the worker thread; the node feeds frames and publishes outcomes."""

    def __init__(self, pipeline: LocalizationPipeline, provider: PriorProvider,
                 config: RuntimeConfig, decode: Callable[[Any], np.ndarray],
                 on_outcome: Callable[[QueryOutcome], None],
                 encoded: Callable[[Any], bytes | None] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 stats: RuntimeStats | None = None, max_waiters: int = 2) -> None:
        self.pipeline, self.provider, self.config = pipeline, provider, config
        self._waiters = threading.BoundedSemaphore(max(1, max_waiters))
        self._decode, self._encoded, self._on_outcome = decode, encoded, on_outcome
        self._clock = clock
        self.stats = stats if stats is not None else RuntimeStats(provider.name, config.mode)
        self._cond = threading.Condition()
        self._slot: Frame | None = None
        self._last_used: Frame | None = None
        self._ticket: RelocalizeTicket | None = None
        self._last_start = -float("inf")
        self._stop = False
        self.busy = False
        self._decode_log = Throttle(5.0)
        self._reload_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="vlm_vpr_query", daemon=True)

    # -- called from ROS callbacks ---------------------------------------------------------------
    def on_frame(self, frame: Frame) -> None:
        """Store ``frame`` as the latest one (O(1); never decodes, never blocks on a query)."""
        frame.received = self._clock()
        with self._cond:
            dropped = self._slot is not None
            self._slot = frame
            self.stats.frame_received(dropped)
            self._cond.notify_all()

    def request_relocalize(self) -> RelocalizeTicket:
        """Force a query on the latest fresh frame (or the next one); coalesces requests."""
        with self._cond:
            self.stats.count("relocalize_requests")
            if self._ticket is None:
                self._ticket = RelocalizeTicket()
            self._cond.notify_all()
            return self._ticket

    def reload_map(self) -> tuple[bool, str]:
        """Re-read the map from disk and swap it in between two queries (the running query
        finishes on the map it started with; the next one uses the new map). On failure the
        current map stays in use. Returns (success, one-line message)."""
        with self._reload_lock:  # one reload at a time; queries keep running meanwhile
            old = self.pipeline
            t0 = time.monotonic()
            try:
                new = old.reloaded()
            except VlmVprError as exc:
                self.stats.count("map_reload_failures")
                log.error("map reload failed, keeping the current map: %s", exc)
                return False, f"map reload failed, the current map stays in use: {exc}"
            with self._cond:
                self.pipeline = new
            self.stats.count("map_reloads")
            om, nm = old.map, new.map
            msg = (f"map {nm.path} reloaded in {time.monotonic() - t0:.1f} s: "
                   f"{om.n_references} -> {nm.n_references} references, {len(om.submaps)} -> "
                   f"{len(nm.submaps)} submaps (generation {om.manifest.get('generation', 0)} -> "
                   f"{nm.manifest.get('generation', 0)})")
            log.info("%s", msg)
            return True, msg

    def relocalize(self, wait_s: float, fix_topic: str = "fix") -> tuple[bool, str]:
        """Answer one relocalize call: (success, sentence) within ``wait_s`` at most.

        Every call joins the one pending request (concurrent calls share one query). At most
        ``max_waiters`` calls wait for its outcome at a time (each holds an executor thread);
        the others are answered at once that the shared relocalization is scheduled, so a burst
        of calls never starves the executor and every call gets an answer."""
        t0 = time.monotonic()
        ticket = self.request_relocalize()
        if wait_s <= 0:
            return True, ("relocalization scheduled on the latest or next frame; the fix will "
                          f"be published on {fix_topic}")
        if not self._waiters.acquire(blocking=False):
            return False, ("busy: a relocalization is already scheduled and shared by the "
                           f"pending requests; its fix will be published on {fix_topic}")
        try:
            outcome = ticket.wait(wait_s)
        finally:
            self._waiters.release()
        return outcome_summary(outcome, time.monotonic() - t0)

    # -- lifecycle -----
    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 5.0, close_provider: bool = True) -> None:
        with self._cond:
            self._stop = True
            ticket, self._ticket = self._ticket, None
            self._cond.notify_all()
        if ticket is not None:
            ticket.finish(None)
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        if close_provider:
            self.provider.close()

    # -- worker -----
    def _fresh(self, frame: Frame | None, now: float) -> bool:
        return frame is not None and now - frame.received <= self.config.max_frame_age_s

    def _next_job(self) -> tuple[Frame, RelocalizeTicket | None] | None:
        """Block until a query is due; None when stopping."""
        with self._cond:
            while not self._stop:
                now = self._clock()
                if now < self._last_start:  # the clock jumped back (bag loop, sim reset)
                    self._last_start = -float("inf")
                if self._ticket is not None:
                    frame = None
                    if self._fresh(self._slot, now):
                        frame, self._slot = self._slot, None
                    elif self._slot is None and self._fresh(self._last_used, now):
                        frame = self._last_used
                    if frame is not None:
                        ticket, self._ticket = self._ticket, None
                        return frame, ticket
                    if self._slot is not None:  # stale frame: wait for the next one
                        self._slot = None
                        self.stats.count("frames_dropped")
                    self._cond.wait(0.5)
                    continue
                if self.config.mode == "continuous" and self._slot is not None:
                    wait = self._last_start + self.config.min_period_s - now
                    if wait <= 0:
                        frame, self._slot = self._slot, None
                        return frame, None
                    self._cond.wait(min(wait, 0.1))  # the clock may be sim time
                    continue
                self._cond.wait(0.5)
        return None

    def _run(self) -> None:
        while True:
            job = self._next_job()
            if job is None:
                return
            frame, ticket = job
            self._last_start = self._clock()
            self.busy = True
            outcome = QueryOutcome(frame, "relocalize" if ticket else "continuous")
            try:
                self._process(outcome)
            except Exception as exc:  # noqa: BLE001 - the worker must outlive any bad query
                log.exception("query on frame %s failed", frame.key)
                outcome.error = f"{type(exc).__name__}: {exc}"
            outcome.finished = time.monotonic()
            self._last_used = frame
            if self._stop:  # shutting down: the query was cut short, publish nothing
                self.busy = False
                if ticket is not None:
                    ticket.finish(None)
                return
            self.stats.record(outcome.hypothesis, outcome.error, outcome.timings_ms)
            try:
                self._on_outcome(outcome)
            except Exception:  # noqa: BLE001 - a publishing failure must not stop the worker
                log.exception("publishing the outcome of frame %s failed", frame.key)
            self.busy = False
            if ticket is not None:  # after publishing: the fix is out when the caller hears
                ticket.finish(outcome)

    def _process(self, out: QueryOutcome) -> None:
        t0 = out.started = time.monotonic()
        frame = out.frame
        try:
            rgb = self._decode(frame.msg)
        except ImageDecodeError as exc:
            out.error = f"undecodable frame: {exc}"
            self.stats.decode_error(str(exc))
            if self._decode_log.ready():
                log.warning("skipping a frame that cannot be decoded (%d so far): %s",
                            self.stats.snapshot()["decode_errors"], exc)
            return
        self.stats.count("frames_processed")
        t1 = time.monotonic()
        encoded = self._encoded(frame.msg) if self._encoded else None
        future = self._request_prior(PriorQuery(image=rgb, encoded=encoded, key=frame.key))
        pipe = self.pipeline  # one map for the whole query, even if reload_map() swaps it now
        try:
            desc = pipe.describe(rgb)
        except VlmVprError as exc:
            future.cancel()
            out.error = f"descriptor failed: {exc}"
            return
        t2 = time.monotonic()
        prior = self._await_prior(future, t1)
        t3 = time.monotonic()
        try:
            hyp = pipe.localize_descriptor(desc, prior)
        except VlmVprError as exc:  # e.g. a map file truncated after start (maps/store.py)
            out.error = f"localization failed: {exc}"
            return
        t4 = time.monotonic()
        out.hypothesis = hyp
        out.timings_ms = {
            "decode_ms": (t1 - t0) * 1e3, "descriptor_ms": (t2 - t1) * 1e3,
            "prior_wait_ms": (t3 - t2) * 1e3, "prior_latency_ms": prior.latency_s * 1e3,
            **hyp.timings_ms, "query_ms": (t4 - t0) * 1e3,
        }

    def _request_prior(self, query: PriorQuery) -> "cf.Future[PriorResult]":
        try:
            return self.provider.request(query)
        except Exception as exc:  # noqa: BLE001 - failures are values (priors/base.py)
            fut: cf.Future[PriorResult] = cf.Future()
            fut.set_result(PriorResult.failure(self.provider.name, f"error: {exc}"))
            return fut

    def _await_prior(self, future: "cf.Future[PriorResult]", t_start: float) -> PriorResult:
        """Wait for the prior until ``prior_timeout_s`` after its request (or stop)."""
        deadline = t_start + self.config.prior_timeout_s
        while not future.done():
            left = deadline - time.monotonic()
            if left <= 0 or self._stop:
                future.cancel()
                reason = "timeout" if left <= 0 else "shutdown"
                return PriorResult.failure(self.provider.name, reason,
                                           latency_s=time.monotonic() - t_start)
            cf.wait([future], timeout=min(left, 0.2))
        try:
            result = future.result()
        except Exception as exc:  # noqa: BLE001 - includes CancelledError
            return PriorResult.failure(self.provider.name, f"error: {exc}",
                                       latency_s=time.monotonic() - t_start)
        if not isinstance(result, PriorResult):
            return PriorResult.failure(self.provider.name, "error: provider returned "
                                       f"{type(result).__name__}")
        return result


def outcome_summary(outcome: QueryOutcome | None, waited_s: float) -> tuple[bool, str]:
    """(success, human-readable sentence) answering a relocalize request."""
    if outcome is None:
        return False, (f"relocalization scheduled, no result within {waited_s:.1f} s (waiting "
                       "for a frame or for the prior); the fix will be published on 'fix'")
    frame = outcome.frame
    if outcome.hypothesis is None:
        return False, f"relocalization on frame {frame.key} gave no fix: {outcome.error}"
    h = outcome.hypothesis
    pr = h.prior_result
    if h.prior is not None:
        prior = f"prior {h.prior.source} ({h.prior.lat:.4f}, {h.prior.lon:.4f})"
    else:
        prior = f"no prior ({pr.reason if pr else 'none'}): global retrieval"
    flag = f" FLAGGED [{'|'.join(h.flags)}]" if h.flagged else ""
    took = outcome.finished - outcome.started
    what = "relocalized frame" if outcome.trigger == "relocalize" else "fix for frame"
    return True, (f"{what} {frame.key}: lat {h.lat:.6f}, lon {h.lon:.6f}, "
                  f"sigma {h.uncertainty_m:.0f} m, reference {h.ref_id}, submap {h.submap}, "
                  f"{prior}, {len(h.candidates)} candidates, {took:.2f} s{flag}")
