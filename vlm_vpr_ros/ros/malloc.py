"""glibc malloc settings of the node process (RSS flat under a camera; docs/node.md)."""

from __future__ import annotations

import ctypes
import os

#: glibc's mallopt parameter for the number of malloc arenas
_M_ARENA_MAX = -8


def tune_malloc(arenas: int = 2) -> bool:
    """Cap glibc's malloc arenas (unless ``MALLOC_ARENA_MAX`` is set): every executor and
    worker thread otherwise gets an arena of its own (up to 8 per core), each keeping its
    high-water mark of freed image buffers, so the node's RSS creeps up for many minutes under
    a camera. True when applied (glibc only; elsewhere a no-op). :func:`trim_malloc` hands
    freed memory back to the OS (called with the diagnostics, at most once a minute)."""
    if os.environ.get("MALLOC_ARENA_MAX"):
        return False
    try:
        return bool(ctypes.CDLL("libc.so.6").mallopt(_M_ARENA_MAX, int(arenas)))
    except (OSError, AttributeError):
        return False


def trim_malloc() -> None:
    """glibc ``malloc_trim(0)``: return the free memory of every arena to the OS."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
