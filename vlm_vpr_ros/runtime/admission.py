"""Who may wait for an answer, and who is still waiting (pure, no ROS).

The node's request paths (docs/node.md "Request paths") share two counts:

* :class:`WaiterLimit`, the admission limit: at most :data:`MAX_WAITERS` relocalize callers
  wait for the shared outcome at once (each holds an executor thread; the node gives its
  executor that many threads more than it needs otherwise). A caller beyond it is answered at
  once, ``busy`` (:meth:`vlm_vpr_ros.runtime.worker.QueryRuntime.relocalize_request`);
* :class:`CallGate`, the callers in progress on every request path, so that each of them has
  its answer before the node destroys its services and action server (cleanup, shutdown,
  SIGINT); a closed gate admits nobody new.
"""

from __future__ import annotations

import threading
import time

#: the admission limit: relocalize callers (all request paths together) that may wait for the
#: shared outcome at once; a caller beyond it is answered at once, ``busy``
MAX_WAITERS = 32


class WaiterLimit:
    """At most ``limit`` callers wait at once (:data:`MAX_WAITERS` by default; at least 1)."""

    def __init__(self, limit: int = MAX_WAITERS) -> None:
        self._free = threading.BoundedSemaphore(max(1, limit))

    def enter(self) -> bool:
        """Take a waiting place at once (True), or False: the limit is reached (busy)."""
        return self._free.acquire(blocking=False)

    def leave(self) -> None:
        self._free.release()


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

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until no caller is in progress (True) or ``timeout_s`` passed (False)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            return self._cond.wait_for(lambda: self._n <= 0,
                                       max(0.0, deadline - time.monotonic()))
