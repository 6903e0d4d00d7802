"""The node's request paths, one policy for all (docs/node.md "Request paths"), ROS edge only.

Every request path of the node — the ``relocalize*`` and ``map_reload`` Trigger services, the
``relocalize_typed`` service and the ``relocalize`` action's goal, cancel and result services —
is created with :data:`REQUEST_QOS`: one bounded, deep request queue, so a burst of callers is
queued and answered instead of dropped by a 10-deep default queue (rclpy's services and action
servers default to depth 10: 80 goals sent at once got 10 answers, 70 callers waited forever).

Admission: at most :data:`~vlm_vpr_ros.runtime.worker.MAX_WAITERS` callers wait for an answer
at once (all paths together, one executor thread each); a caller beyond that is answered at
once, ``OUTCOME_BUSY`` (the shared relocalization is scheduled and its fix goes out on
``fix``). An action goal beyond the limit is *accepted and aborted at once* with
``OUTCOME_BUSY`` in its result, so a behaviour tree can tell "busy, retry" from "invalid"
(a rejected goal carries no reason). A caller's wait is bounded by :data:`MAX_TIMEOUT_S`.

:class:`CallGate` counts the callers in progress so that every one of them has its answer
before the services and the action server are destroyed (cleanup, shutdown, SIGINT).
"""

from __future__ import annotations

import math
import threading
import time

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from vlm_vpr_ros.runtime.params import PARAMETER_SPECS

#: requests queued per service (and per action service) before the oldest unread is dropped;
#: every queued request is taken within a few ms (a waiting caller holds a thread, a caller
#: beyond the admission limit is answered BUSY at once), so the queue drains as fast as it fills
REQUEST_QUEUE_DEPTH = 1000
#: the QoS of every request path of the node (services, action goal/cancel/result services)
REQUEST_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=REQUEST_QUEUE_DEPTH,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
#: the longest wait a caller may ask for (``timeout_s``): relocalize_wait_s's upper bound
MAX_TIMEOUT_S = float(PARAMETER_SPECS["relocalize_wait_s"].range[1])
#: how long cleanup / shutdown / SIGINT wait for the callers in progress to be answered
DRAIN_S = 5.0


def timeout_problem(timeout_s: float, allow_default: bool) -> str:
    """Why a requested timeout is refused ("" when fine); 0 means the node's default only
    where ``allow_default`` (the service); at most :data:`MAX_TIMEOUT_S`."""
    t = float(timeout_s)
    if allow_default and t == 0.0:
        return ""
    if not math.isfinite(t) or t <= 0:
        return f"timeout_s must be a positive finite number of seconds, got {t}"
    if t > MAX_TIMEOUT_S:
        return (f"timeout_s must be at most {MAX_TIMEOUT_S:g} s (the range of "
                f"relocalize_wait_s), got {t:g}")
    return ""


class CallGate:
    """The callers in progress on the request paths; closed: no new one is admitted."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._n = 0
        self._open = True

    def enter(self, force: bool = False) -> bool:
        """A caller starts (False: the node is closing, answer it without waiting);
        ``force``: counted even then (an action goal already accepted)."""
        with self._cond:
            if not self._open and not force:
                return False
            self._n += 1
            return True

    def leave(self) -> None:
        with self._cond:
            self._n -= 1
            self._cond.notify_all()

    @property
    def open(self) -> bool:
        return self._open

    @property
    def in_progress(self) -> int:
        with self._cond:
            return self._n

    def close(self) -> None:
        with self._cond:
            self._open = False

    def reopen(self) -> None:
        with self._cond:
            self._open = True

    def wait_idle(self, timeout_s: float = DRAIN_S) -> bool:
        """Block until no caller is in progress (True) or ``timeout_s`` passed (False)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            return self._cond.wait_for(lambda: self._n <= 0,
                                       max(0.0, deadline - time.monotonic()))
