"""glibc malloc settings of the node process (RSS flat under a camera; docs/node.md)."""

from __future__ import annotations

import ctypes
import os

#: glibc's mallopt parameters: the number of malloc arenas; the size from which a block is
#: mmapped (and so returned to the OS when freed)
_M_ARENA_MAX = -8
_M_MMAP_THRESHOLD = -3
#: camera frames (640x480 rgb8: 900 KiB) and feature blocks are above it: always mmapped
MMAP_THRESHOLD = 256 * 1024


def tune_malloc(arenas: int = 2) -> bool:
    """Cap glibc's malloc arenas and fix its mmap threshold (unless ``MALLOC_ARENA_MAX`` is
    set): every executor and worker thread otherwise gets an arena of its own (up to 8 per
    core), and glibc raises the mmap threshold after the first large free, so later 900 KiB
    frames come from those arenas and fragment them; the node's RSS then creeps up for many
    minutes under a camera. True when applied (glibc only; elsewhere a no-op).
    :func:`trim_malloc` hands freed memory back to the OS (with the diagnostics, at most once
    a minute)."""
    if os.environ.get("MALLOC_ARENA_MAX"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(_M_ARENA_MAX, int(arenas))
                    and libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
    except (OSError, AttributeError):
        return False


def trim_malloc() -> None:
    """glibc ``malloc_trim(0)``: return the free memory of every arena to the OS."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
