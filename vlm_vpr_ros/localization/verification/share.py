"""The candidates of one verification shared between the calling thread and helper threads.

Each candidate's work — its match (a BLAS product on one thread) and its MAGSAC fit — is
independent of the others' and releases the GIL for almost all of its time, so K = 20
candidates spread over the usable cores take about 1/cores of the time (issue 31: 110 ms on
one core of a quiet 2-core AVX2 EPYC; docs/verification.md). Each candidate is computed whole
by one thread, with the same code as on one thread: the same floats, the same matches and the
same MAGSAC draws (OpenCV seeds each fit), so the answers do not depend on the thread count
(``tests/test_verify_threads.py``).

Hand-written rather than ``ThreadPoolExecutor.map``: the calling thread works too and takes the
next candidate from the same counter as the helpers, so it never waits for a helper that has not
been given a core (a busy machine, a node's other threads) — it only waits, at the end, for the
candidates a helper has already started. The previous attempt split each product's rows over two
threads (a hand-off per product, 40 per query): it lost time on a quiet machine.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

from vlm_vpr_ros.threads import usable_cores

T = TypeVar("T")

#: most threads one verification uses (the calling thread + helpers): K = 20 candidates of
#: ~5 ms each gain little from more, and a node has other threads
MAX_THREADS = 4
_pool: tuple[int, int, ThreadPoolExecutor] | None = None  # (pid, helpers, pool)
_pool_lock = threading.Lock()


def resolve_threads(threads: int) -> int:
    """Threads of one verification: ``threads`` when > 0, else (auto) the usable cores up to
    :data:`MAX_THREADS`."""
    return int(threads) if threads > 0 else min(usable_cores(), MAX_THREADS)


def _helpers(n: int) -> ThreadPoolExecutor:
    """A pool of at least ``n`` helper threads, created once per process (a forked child gets
    its own: a fork copies the pool object but not its threads)."""
    global _pool
    with _pool_lock:
        if _pool is None or _pool[0] != os.getpid() or _pool[1] < n:
            if _pool is not None and _pool[0] == os.getpid():
                _pool[2].shutdown(wait=False)  # a smaller one: its threads end when idle
            _pool = (os.getpid(), n, ThreadPoolExecutor(max_workers=n,
                                                        thread_name_prefix="verify"))
        return _pool[2]


class _Work:
    """``fn(0..n-1)`` claimed one index at a time from one counter."""

    def __init__(self, fn: Callable[[int], T], n: int) -> None:
        self.fn, self.n = fn, n
        self.next = 0
        self.lock = threading.Lock()
        self.results: list = [None] * n
        self.errors: list[BaseException | None] = [None] * n
        self.done = [threading.Event() for _ in range(n)]

    def _claim(self) -> int:
        with self.lock:
            i = self.next
            self.next += 1
            return i

    def run(self) -> None:
        while (i := self._claim()) < self.n:
            try:
                self.results[i] = self.fn(i)
            except BaseException as exc:  # handed to the caller, raised there
                self.errors[i] = exc
            finally:
                self.done[i].set()


def map_shared(fn: Callable[[int], T], n: int, threads: int = 1) -> list[T]:
    """``[fn(0), ..., fn(n - 1)]``, computed by the calling thread and up to ``threads - 1``
    helpers; the first error (in index order) is raised after every started call ended."""
    helpers = min(int(threads), n) - 1
    if helpers <= 0:
        return [fn(i) for i in range(n)]
    work = _Work(fn, n)
    pool = _helpers(helpers)
    for _ in range(helpers):
        pool.submit(work.run)
    work.run()  # the caller claims until none is left; then only started calls are waited for
    for event in work.done:
        event.wait()
    for exc in work.errors:
        if exc is not None:
            raise exc
    return work.results
