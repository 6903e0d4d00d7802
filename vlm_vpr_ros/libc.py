"""The C library through ctypes, loaded once for the few calls Python does not wrap: the
map's change notice (``inotify``, :mod:`vlm_vpr_ros.maps.watch`), memory mappings that keep
no file descriptor (``mmap``, :mod:`vlm_vpr_ros.maps.mapped`) and glibc's malloc settings
(:mod:`vlm_vpr_ros.ros.malloc`). Each caller checks for the functions it needs and declares
their argument types itself."""

from __future__ import annotations

import ctypes
import functools


@functools.lru_cache(maxsize=1)
def libc() -> ctypes.CDLL | None:
    """The process's C library (its symbols as the dynamic linker resolves them, with
    ``errno`` kept for :func:`ctypes.get_errno`); None where ctypes cannot load it (no
    ``CDLL(None)`` on Windows)."""
    try:
        return ctypes.CDLL(None, use_errno=True)
    except (OSError, TypeError):
        return None
