"""Thread settings of one query: BLAS on the calling thread, the cores a process may use, and
each thread's scratch buffers.

A query's products are small (a VLAD assignment of ~1,000 × 128 by 64 words, a PCA projection,
~20 verification products of ~700 × ~750 × 128): an OpenBLAS thread team gains nothing on them,
and after each call its workers spin for a while before they sleep. On a 2-core machine those
spinning workers take the core the query's other work needs (issue 31, quiet 2-core AVX2 EPYC,
SF night queries: descriptor 90 → 72 ms and the verification stage on two threads 99 → 62 ms
once every BLAS call of the query ran on one thread). So the query path holds
:func:`one_blas_thread` and uses the second core explicitly, where the work divides into whole
pieces (verification's candidates: :mod:`vlm_vpr_ros.localization.verification.share`).

The limit covers every BLAS that threadpoolctl finds (numpy's OpenBLAS, FAISS's, OpenCV's) and
is restored on leaving (threadpoolctl's context manager). How far a setting reaches depends on
the library: an OpenMP build's (FAISS's) is per thread, and an OpenBLAS pthreads build's
setting made on one thread was seen by the others in some orders and not in others (measured
here, OpenBLAS 0.3.31 and 0.3.15). So every thread that runs query products holds it itself
(verification's helpers too), and a worker thread may leave BLAS on one thread after its
queries — which its next queries want anyway. The controller
that finds the libraries is made once (its search costs ~0.5 ms; a limit then ~20 µs) and again
when a library that brings its own BLAS is imported later.

:func:`scratch` keeps a query's large temporaries (verification's similarity matrix, the
re-rank's rows) in buffers of the thread, reused from query to query: allocated per query, glibc
maps such blocks fresh and the kernel zero-fills them every time, and under the node's malloc
settings of issue 29 (blocks from 256 KiB mmapped) that cost as much as the work itself
(issue 31: the verification stage 122-136 against 56-70 ms on one thread; the re-rank of 800
fp16 rows 4.6 ms against 0.35 ms).
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import threading
from typing import Any, Iterator

import numpy as np

_controller: tuple[tuple[bool, ...], Any] | None = None
_lock = threading.Lock()
#: modules whose import loads a BLAS of their own
_BLAS_MODULES = ("numpy", "faiss", "cv2", "torch", "scipy")
_scratch = threading.local()


def _blas_controller() -> Any:
    global _controller
    from threadpoolctl import ThreadpoolController

    loaded = tuple(m in sys.modules for m in _BLAS_MODULES)
    with _lock:
        if _controller is None or _controller[0] != loaded:
            _controller = (loaded, ThreadpoolController())
        return _controller[1]


def one_blas_thread() -> Any:
    """Context manager: every BLAS on one thread while it is held (module docstring)."""
    return _blas_controller().limit(limits=1, user_api="blas")


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity, else the CPU count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def scratch(name: str, shape: tuple[int, ...], dtype: Any = np.float32) -> np.ndarray:
    """An array of ``shape`` and ``dtype`` in a buffer of this thread kept between calls (one
    per name and dtype, grown when too small); its content is whatever the last user left.
    Only for temporaries that no result refers to, used by one caller at a time."""
    size = math.prod(shape)
    try:
        bufs = _scratch.bufs
    except AttributeError:
        bufs = _scratch.bufs = {}
    key = (name, np.dtype(dtype).char)
    buf = bufs.get(key)
    if buf is None or buf.size < size:
        buf = bufs[key] = np.empty(max(size, int(1.25 * (0 if buf is None else buf.size))),
                                   dtype)
    return buf[:size].reshape(shape)


_TORCH_THREADS = threading.Lock()


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op threads at ``n`` for the block (0: unchanged), restored after: the
    learned local features (XFeat, DISK, ALIKED, LightGlue) run one thread per call by default.

    XFeat on one 640 px frame is 67 ms of CPU on one thread (AMD EPYC, 2 cores); with torch's
    default of one thread per core it took 925 ms of CPU and 4.2 s of wall time on the same
    2-core machine while other work ran: its OpenMP team spins for a core another thread
    holds, as OpenBLAS's did (above). The setting is process-wide: blocks run one at a time.
    torch is imported here only when a block asks for threads (the weight-free default never
    imports it)."""
    if n <= 0:
        yield
        return
    import torch

    with _TORCH_THREADS:
        before = torch.get_num_threads()
        if before != n:
            torch.set_num_threads(n)
        try:
            yield
        finally:
            if before != n:
                torch.set_num_threads(before)
