"""The query logic of the ROS node, without ROS: latest-frame slot, worker, statistics.

Threads: the image callback only calls :meth:`QueryRuntime.on_frame`, which stores the still
undecoded message in a one-frame slot (a newer frame replaces an unused one: *dropped by design*,
counted). One worker thread takes frames when a query is due — every ``min_period_s`` in
``continuous`` mode, on :meth:`QueryRuntime.request_relocalize` in both modes (kinds of requests:
:mod:`vlm_vpr_ros.runtime.relocalize`) — decodes the frame, starts the prior request
(asynchronous, see :mod:`vlm_vpr_ros.priors.provider`), computes the descriptor meanwhile, waits
for the prior at most ``prior_timeout_s``, localizes (flagged global retrieval when the prior
failed) and hands a :class:`QueryOutcome` to ``on_outcome``. Nothing here queues more than one
frame and one pending relocalization per kind.

Runtime tuning: :meth:`QueryRuntime.update` swaps the rate/timeout settings and the localizer's
per-query settings (``top_p`` ...); the next query uses them, a running query keeps its own.

Time: ``min_period_s`` and frame ages (``max_frame_age_s``) are measured on the ``clock`` given
to :class:`QueryRuntime` (the node passes its ROS clock, so they follow ``/clock`` under
``use_sim_time``; default: ``time.monotonic``). A clock that jumps backwards (a bag replayed in
a loop) restarts the period instead of stalling the queries.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from vlm_vpr_ros.errors import ConfigError, ImageDecodeError, VlmVprError
from vlm_vpr_ros.localization.localizer import LocalizerConfig
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
from vlm_vpr_ros.priors.provider import PriorProvider, PriorQuery, PriorResult
from vlm_vpr_ros.runtime import debug_view
from vlm_vpr_ros.runtime.outcome import Frame, QueryOutcome
from vlm_vpr_ros.runtime.relocalize import (RelocalizeKind, RelocalizeResult,
                                            RelocalizeTicket, await_answer, no_answer_text,
                                            outcome_summary)
from vlm_vpr_ros.redact import redact
from vlm_vpr_ros.runtime.stats import RuntimeStats, Throttle

log = logging.getLogger(__name__)
MODES = ("continuous", "on_trigger")
#: the admission limit: relocalize callers (all request paths together) that may wait for the
#: shared outcome at once (the node gives its executor this many threads more than it needs
#: otherwise); a caller beyond it is answered at once, ``busy`` (docs/node.md "Request paths")
MAX_WAITERS = 32
#: LocalizerConfig fields that runtime tuning may change (read per query by the localizer)
TUNABLE_LOCALIZER = ("top_p", "fusion", "use_submaps", "rerank", "n_submaps")
__all__ = ["Frame", "MAX_WAITERS", "QueryOutcome", "QueryRuntime", "RelocalizeKind",
           "RelocalizeTicket", "RuntimeConfig", "outcome_summary", "reload_pipeline"]


def reload_pipeline(pipe: LocalizationPipeline) -> tuple[LocalizationPipeline | None, str]:
    """``pipe``'s map re-read from disk, or (None, why, redacted) on any failure: the
    ``map_reload`` service answers it and the node keeps its current map."""
    try:
        return pipe.reloaded(), ""
    except (VlmVprError, OSError) as exc:
        log.error("map reload failed, keeping the current map: %s", exc)
        return None, redact(exc)
    except Exception as exc:  # noqa: BLE001 - a service call must not stop the node
        log.exception("map reload failed, keeping the current map")
        return None, redact(f"internal error {type(exc).__name__}: {exc}")


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


class QueryRuntime:
    """Owns the worker thread; the node feeds frames and publishes outcomes."""

    def __init__(self, pipeline: LocalizationPipeline, provider: PriorProvider,
                 config: RuntimeConfig, decode: Callable[[Any], np.ndarray],
                 on_outcome: Callable[[QueryOutcome], None],
                 encoded: Callable[[Any], bytes | None] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 stats: RuntimeStats | None = None, max_waiters: int = MAX_WAITERS) -> None:
        self.pipeline, self.provider, self.config = pipeline, provider, config
        self.localizer_config: LocalizerConfig = pipeline.localizer.config
        #: verification settings tuned at runtime (status policy, verify_top_k); None: as opened
        self.verification: tuple[Any, int | None] | None = None
        self.keep_images = False  # hand the decoded frame to on_outcome (debug view)
        self._waiters = threading.BoundedSemaphore(max(1, max_waiters))
        self._decode, self._encoded, self._on_outcome = decode, encoded, on_outcome
        self._clock = clock
        self.stats = stats if stats is not None else RuntimeStats(provider.name, config.mode)
        self._cond = threading.Condition()
        self._slot: Frame | None = None
        self._last_used: Frame | None = None
        self._seq = 0
        self._tickets: dict[RelocalizeKind, RelocalizeTicket] = {}
        #: the running query: (frame, prior asked, the requests it answers); requests for the
        #: latest frame join it while its frame is fresh enough for them
        self._inflight: tuple[Frame, bool, dict[RelocalizeKind, RelocalizeTicket]] | None = None
        self._last_start = -float("inf")
        self._stage_now = "asking_prior"
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
            self._seq += 1
            frame.seq = self._seq
            dropped = self._slot is not None
            self._slot = frame
            self.stats.frame_received(dropped)
            self._cond.notify_all()

    def request_relocalize(self, kind: RelocalizeKind = RelocalizeKind(),
                           wait: bool = False) -> RelocalizeTicket:
        """Force a query (ignoring ``min_period_s``, in both modes) on the frame ``kind`` asks
        for; requests of one kind made while one is pending share it. ``wait``: the caller
        attaches as a waiter (:func:`~vlm_vpr_ros.runtime.relocalize.await_answer`); else the
        request is fire-and-forget and its answer is published whoever waits."""
        with self._cond:
            self.stats.count("relocalize_requests")
            ticket = self._tickets.get(kind) or self._join_inflight(kind)
            if ticket is None:
                ticket = self._tickets[kind] = RelocalizeTicket(kind, self._seq)
            ticket.attach() if wait else ticket.detach()
            self._cond.notify_all()
            return ticket

    def _give_up(self, ticket: RelocalizeTicket) -> None:
        """A waiter left ``ticket``: drop it while still pending if nobody wants it now."""
        with self._cond:
            if self._tickets.get(ticket.kind) is ticket and ticket.abandoned:
                del self._tickets[ticket.kind]
                self.stats.count("relocalize_abandoned")

    def _stage(self, name: str) -> None:
        """The running query reached stage ``name``: its callers hear it (action feedback)."""
        with self._cond:
            self._stage_now = name
            for ticket in (self._inflight[2].values() if self._inflight else ()):
                ticket.stage(name)

    def _join_inflight(self, kind: RelocalizeKind) -> RelocalizeTicket | None:
        """The running query's ticket for a ``latest`` request it can answer (its frame was
        fresh when the query started and the prior setting matches), so a caller arriving
        during a slow VLM call shares that call instead of queueing another; None otherwise
        (caller holds the lock). A ``next`` request never joins: the running query's frame
        predates it."""
        if self._inflight is None or kind.frame != "latest":
            return None
        frame, use_prior, served = self._inflight
        ticket = RelocalizeTicket(kind, self._seq)
        if use_prior != kind.use_prior or not ticket.accepts(frame, self._last_start,
                                                             self.config.max_frame_age_s):
            return None
        ticket = served.setdefault(kind, ticket)
        ticket.stage(self._stage_now)
        return ticket

    def update(self, config: RuntimeConfig | None = None,
               localizer: LocalizerConfig | None = None, status: Any = None,
               verify_top_k: int | None = None) -> None:
        """New settings from the next query on (runtime tuning); a running query keeps its
        own. ``localizer``: per-query settings only (top_p, fusion, submaps, rerank);
        ``status`` (a StatusPolicy) and ``verify_top_k``: verification (docs/verification.md)."""
        with self._cond:
            if status is not None or verify_top_k is not None:
                self.verification = (status, verify_top_k)
            if config is not None:
                self.config = config
                self.stats.mode = config.mode
            if localizer is not None:
                self.localizer_config = localizer
            self._cond.notify_all()  # a shorter min_period_s applies to the current wait

    def reload_map(self) -> tuple[bool, str]:
        """Re-read the map from disk and swap it in between two queries (the running query
        finishes on the map it started with; the next one uses the new map). On failure the
        current map stays in use. Returns (success, one-line message)."""
        with self._reload_lock:  # one reload at a time; queries keep running meanwhile
            old = self.pipeline
            t0 = time.monotonic()
            new, why = reload_pipeline(old)
            if new is None:
                self.stats.count("map_reload_failures")
                return False, f"map reload failed, the current map stays in use: {why}"
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

    def relocalize(self, wait_s: float, fix_topic: str = "fix",
                   kind: RelocalizeKind = RelocalizeKind()) -> tuple[bool, str]:
        """Answer one relocalize Trigger call: (success, sentence) within ``wait_s`` at most
        (:meth:`relocalize_request`). ``wait_s`` 0: not waited, never success."""
        res = self.relocalize_request(kind, wait_s)
        if res.outcome is None:
            return False, no_answer_text(res, fix_topic, kind.label)
        return outcome_summary(res.outcome, res.waited_s, fix_topic)

    def relocalize_request(self, kind: RelocalizeKind, wait_s: float,
                           cancelled: Callable[[], bool] | None = None,
                           on_stage: Callable[[str], None] | None = None) -> RelocalizeResult:
        """One relocalize caller (Trigger, typed service, action): joins the pending request
        of its kind (concurrent calls share one query) and waits for that shared outcome at
        most ``wait_s`` (docs/node.md "Relocalize rules"). ``wait_s`` <= 0: fire and forget
        (code ``scheduled``). Each waiting call holds an executor thread, so at most
        ``max_waiters`` wait at once; a call beyond that is told the shared relocalization is
        scheduled (code ``busy``; never refused)."""
        if wait_s <= 0:
            self.request_relocalize(kind)
            return RelocalizeResult("scheduled")
        if not self._waiters.acquire(blocking=False):
            self.request_relocalize(kind)
            return RelocalizeResult("busy")
        try:
            ticket = self.request_relocalize(kind, wait=True)
            return await_answer(ticket, wait_s, cancelled, on_stage, self._give_up)
        finally:
            self._waiters.release()

    # -- lifecycle -----
    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 5.0, close_provider: bool = True) -> None:
        with self._cond:
            self._stop = True
            tickets, self._tickets = list(self._tickets.values()), {}
            if self._inflight is not None:  # its query is cut short and never published
                tickets += list(self._inflight[2].values())
            self._cond.notify_all()
        for ticket in tickets:  # every waiting caller is answered now (not_active)
            ticket.finish(None)
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        if close_provider:
            self.provider.close()

    # -- worker -----
    def _relocalize_job(self, now: float) -> tuple[Frame, list[RelocalizeTicket]] | None:
        """The frame for the oldest pending request and every pending request of the same
        prior setting that this frame also answers; None: wait for a frame (caller holds
        the lock)."""
        for gone in [k for k, t in self._tickets.items() if t.abandoned]:
            del self._tickets[gone]
        if not self._tickets:
            return None
        age = self.config.max_frame_age_s
        first = min(self._tickets.values(), key=lambda t: t.requested)
        frame = None
        if first.accepts(self._slot, now, age):
            frame, self._slot = self._slot, None
        elif self._slot is None and first.accepts(self._last_used, now, age):
            frame = self._last_used
        if frame is None:
            if self._slot is not None and not any(t.accepts(self._slot, now, age)
                                                  for t in self._tickets.values()):
                self._slot = None  # stale, or older than the request: wait for the next one
                self.stats.count("frames_dropped")
            return None
        served = [t for t in self._tickets.values() if t.kind.use_prior == first.kind.use_prior
                  and t.accepts(frame, now, age)]
        for t in served:
            del self._tickets[t.kind]
        return frame, served

    def _next_job(self) -> tuple[Frame, list[RelocalizeTicket]] | None:
        """Block until a query is due; None when stopping."""
        with self._cond:
            while not self._stop:
                now = self._clock()
                if now < self._last_start:  # the clock jumped back (bag loop, sim reset)
                    self._last_start = -float("inf")
                if self._tickets:
                    job = self._relocalize_job(now)
                    if job is not None:
                        return job
                    self._cond.wait(0.5)
                    continue
                if self.config.mode == "continuous" and self._slot is not None:
                    wait = self._last_start + self.config.min_period_s - now
                    if wait <= 0:
                        frame, self._slot = self._slot, None
                        return frame, []
                    self._cond.wait(min(wait, 0.1))  # the clock may be sim time
                    continue
                self._cond.wait(0.5)
        return None

    def _run(self) -> None:
        while True:
            job = self._next_job()
            if job is None:
                return
            frame, tickets = job
            use_prior = all(t.kind.use_prior for t in tickets)
            with self._cond:
                self._last_start = self._clock()
                self._inflight = (frame, use_prior, {t.kind: t for t in tickets})
                self._stage_now = "asking_prior" if use_prior else "retrieving"
                for t in tickets:
                    t.stage(self._stage_now)
            self.busy = True
            outcome = QueryOutcome(frame, "relocalize" if tickets else "continuous")
            try:
                self._process(outcome, use_prior)
            except Exception as exc:  # noqa: BLE001 - the worker must outlive any bad query
                log.exception("query on frame %s failed", frame.key)
                outcome.error = f"{type(exc).__name__}: {exc}"
            outcome.finished = time.monotonic()
            self._last_used = frame
            with self._cond:  # requests from now on wait for the next query
                tickets, self._inflight = list(self._inflight[2].values()), None
            live = [t for t in tickets if t.claim()]  # nobody waits for the others any more
            if tickets and not live:
                self.stats.count("relocalize_abandoned")
                if self.config.mode != "continuous":  # an answer nobody asked for now
                    self.busy = False
                    for ticket in tickets:
                        ticket.finish(None)
                    continue
            outcome.trigger = "relocalize" if live else "continuous"
            tickets = live
            if self._stop:  # shutting down: the query was cut short, publish nothing
                self.busy = False
                for ticket in tickets:
                    ticket.finish(None)
                return
            outcome.error = redact(outcome.error)  # logged, in diagnostics and answers
            self.stats.record(outcome.hypothesis, outcome.error, outcome.timings_ms)
            try:
                self._on_outcome(outcome)
            except Exception:  # noqa: BLE001 - a publishing failure must not stop the worker
                log.exception("publishing the outcome of frame %s failed", frame.key)
            self.busy = False
            for ticket in tickets:  # after publishing: the fix is out when the caller hears
                ticket.finish(outcome)

    def _process(self, out: QueryOutcome, use_prior: bool = True) -> None:
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
        if self.keep_images:
            out.rgb = rgb
        t1 = time.monotonic()
        future = None
        if use_prior:
            encoded = self._encoded(frame.msg) if self._encoded else None
            future = self._request_prior(PriorQuery(image=rgb, encoded=encoded, key=frame.key))
        with self._cond:  # one map and one set of settings for the whole query
            pipe, settings, verification = self.pipeline, self.localizer_config, \
                self.verification
        tuned = {k: getattr(settings, k) for k in TUNABLE_LOCALIZER}
        if any(getattr(pipe.localizer.config, k) != v for k, v in tuned.items()):
            # tuned at runtime: the worker is the localizer's only user between queries
            pipe.localizer.config = dataclasses.replace(pipe.localizer.config, **tuned)
        if verification is not None:
            pipe.tune(*verification)
        try:
            query = pipe.describe_query(rgb)  # + local features for verification
        except VlmVprError as exc:
            if future is not None:
                future.cancel()
            out.error = f"descriptor failed: {exc}"
            return
        t2 = time.monotonic()
        prior = self._await_prior(future, t1) if future is not None else None
        t3 = time.monotonic()
        self._stage("retrieving")
        try:
            hyp = pipe.localizer.localize(query.desc, prior)
            self._stage("verifying")
            hyp = pipe.finish(hyp, query.local)  # = pipe.localize_descriptor, in two stages
        except VlmVprError as exc:  # e.g. a map file truncated after start (maps/store.py)
            out.error = f"localization failed: {exc}"
            return
        t4 = time.monotonic()
        out.hypothesis = hyp
        if self.keep_images:  # the debug view draws the answer's verified matches
            out.matches = debug_view.winner_matches(pipe.verifier, query.local, hyp)
        out.timings_ms = {
            "decode_ms": (t1 - t0) * 1e3, "descriptor_ms": (t2 - t1) * 1e3,
            "prior_wait_ms": (t3 - t2) * 1e3,
            "prior_latency_ms": prior.latency_s * 1e3 if prior is not None else 0.0,
            **hyp.timings_ms, "query_ms": (t4 - t0) * 1e3,
        }

    def _request_prior(self, query: PriorQuery) -> "cf.Future[PriorResult]":
        try:
            return self.provider.request(query)
        except Exception as exc:  # noqa: BLE001 - failures are values (priors/provider.py)
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

