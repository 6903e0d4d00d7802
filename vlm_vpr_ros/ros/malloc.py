"""glibc malloc settings of the node process: RSS flat under a camera, a query's temporaries
reused (docs/node.md).

Three settings, made before any thread starts:

* at most 2 malloc arenas: every executor and worker thread otherwise gets one of its own (up
  to 8 per core), each keeping its freed memory, and the node's RSS crept up under a camera;
* a fixed mmap threshold of 32 MiB (glibc's largest): glibc otherwise raises its threshold
  after the first large free, and where a block lands then depends on the order of frees;
* a trim threshold of 256 MiB: free memory at the top of an arena is kept for the next query
  instead of being handed back at every ``free``.

The last two are issue 31's. A query's large temporaries (OpenCV's SIFT pyramid of a 640x480
frame: ~5 MB per image of the first octave; the VLAD arrays; camera frames of 900 KiB) were
mmapped fresh at every frame with the earlier 256 KiB threshold, and the kernel zero-filled them
every time: 21,800 page faults per frame, the descriptor 92 ms against 43 ms with these
settings (0 faults), 71 ms with glibc's defaults (16,400: its dynamic trim hands the top back).
Freed memory goes back to the OS once a minute instead (:func:`trim_malloc`, with the
diagnostics); ``benchmarks/rss_node.py`` measures the RSS under a camera.
"""

from __future__ import annotations

import os

from vlm_vpr_ros.libc import libc

#: glibc's mallopt parameters
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
#: malloc arenas of the node (glibc's default: up to 8 per core, one per thread)
ARENAS = 2
#: blocks from this size are mmapped (and so returned to the OS when freed): glibc's maximum on
#: 64-bit systems, so a query's temporaries and camera frames come from the arenas
MMAP_THRESHOLD = 32 * 2 ** 20
#: free memory at an arena's top is kept up to this size (a query's working set is reused)
TRIM_THRESHOLD = 256 * 2 ** 20


def tune_malloc(arenas: int = ARENAS) -> bool:
    """Cap glibc's malloc arenas and fix its mmap and trim thresholds (module docstring),
    unless ``MALLOC_ARENA_MAX`` is set (the user's own settings win). True when applied (glibc
    only; elsewhere a no-op). :func:`trim_malloc` hands freed memory back to the OS."""
    if os.environ.get("MALLOC_ARENA_MAX"):
        return False
    lib = libc()
    try:
        return bool(lib.mallopt(_M_ARENA_MAX, int(arenas))
                    and lib.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
                    and lib.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    except AttributeError:  # not glibc (or no C library)
        return False


def trim_malloc() -> None:
    """glibc ``malloc_trim(0)``: return the free memory of every arena to the OS."""
    try:
        libc().malloc_trim(0)
    except AttributeError:  # not glibc (or no C library)
        pass
