"""Change notice for the folders of an open map: whether any of their files may have changed
since a moment, so the per-query file guard (:meth:`vlm_vpr_ros.maps.store.LazySubmap.check_files`)
``stat``s a file again only then.

Why: every query ``stat``s the files it reads (a file truncated under a memory mapping would
crash the process with SIGBUS, a file rewritten in place would give wrong answers). On a map of
many submaps that is ~60 ``stat`` calls per query, each ~10 us right after FAISS has streamed
200 MB through the caches: 0.5-0.6 ms of a 10 ms query on a 100k map (issue 31, AVX-512
EPYC). The guard keeps its per-query promise with one ``read`` of an inotify descriptor instead:

* :meth:`FolderWatch.generation` drains the kernel's events for the watched folders (any
  write, truncation, attribute change, create, delete, move) and returns a number that changes
  whenever there was one; a file whose last passed check was in the current generation is
  unchanged since that check. The kernel queues an event when the change is made, so a change
  made before a query began is seen by that query, as with a ``stat`` (a change made between
  the check and the read is a race either way). A query drains once
  (:meth:`FolderWatch.query`, around ``ReferenceMap.rank_submaps``); a check outside a query
  drains itself.
* The generation also changes once per :data:`REFRESH_S` without events: a change that inotify
  does not report (a write through another process's shared writable mapping) is still seen
  by a ``stat`` within that time.
* Only on local file systems (:data:`LOCAL_FS`, from ``/proc/self/mountinfo``): inotify does
  not see changes made by another machine on NFS, SMB, FUSE or virtiofs mounts, so there, and
  where inotify is missing or its limits are reached (``fs.inotify.max_user_instances``),
  :meth:`generation` returns ``None`` and every query ``stat``s as before.

Hand-written with ctypes: the three libc calls are all it needs (a dependency for them would be
larger than this module, and no kept package here wraps them).
"""

from __future__ import annotations

import array
import contextlib
import ctypes
import fcntl
import logging
import os
import termios
import threading
import time
import weakref
from pathlib import Path
from typing import Iterator

from vlm_vpr_ros.libc import libc

log = logging.getLogger(__name__)

#: seconds after which the generation changes even without events (see the module docstring)
REFRESH_S = 1.0
#: file systems whose changes the local kernel reports to inotify
LOCAL_FS = frozenset({"ext2", "ext3", "ext4", "xfs", "btrfs", "tmpfs", "ramfs", "f2fs", "jfs",
                      "reiserfs", "zfs", "bcachefs", "nilfs2", "overlay"})
_IN_NONBLOCK, _IN_CLOEXEC = 0o4000, 0o2000000
#: modify, attrib, close_write, moved_from, moved_to, create, delete, delete_self, move_self
_MASK = 0x2 | 0x4 | 0x8 | 0x40 | 0x80 | 0x100 | 0x200 | 0x400 | 0x800
_OUTSIDE = object()  # no query on this thread


def _libc() -> ctypes.CDLL | None:
    lib = libc()
    return lib if lib is not None and hasattr(lib, "inotify_init1") else None


def _queued(fd: int) -> int:
    """Bytes of events waiting on an inotify descriptor (``FIONREAD``)."""
    buf = array.array("i", [0])
    fcntl.ioctl(fd, termios.FIONREAD, buf, True)
    return buf[0]


def filesystem_type(path: Path | str, mountinfo: str | None = None) -> str:
    """The type of the file system holding ``path`` ('' when unknown): the longest mount point
    of ``/proc/self/mountinfo`` (or the text ``mountinfo``) that contains it."""
    real = os.path.realpath(path)
    best, kind = "", ""
    if mountinfo is None:
        try:
            mountinfo = Path("/proc/self/mountinfo").read_text()
        except OSError:
            return ""
    for line in mountinfo.splitlines():
        left, _, right = line.partition(" - ")
        fields, rest = left.split(), right.split()
        if len(fields) < 5 or not rest:
            continue
        mount = fields[4].replace("\\040", " ")
        inside = real == mount or real.startswith(mount.rstrip("/") + "/")
        if inside and len(mount) >= len(best):
            best, kind = mount, rest[0]
    return kind


class FolderWatch:
    """inotify on a few folders; see the module docstring."""

    def __init__(self, folders: list[Path]) -> None:
        self._fd: int | None = None
        self._lock = threading.Lock()
        self._generation = 0
        self._since = time.monotonic()
        self._local = threading.local()  # .gen: the generation of this thread's query
        kinds = {filesystem_type(f) for f in folders}
        libc = _libc()
        if not folders or libc is None or not kinds <= LOCAL_FS:
            log.debug("no change notice for %s (file systems %s): stat per query", folders,
                      sorted(kinds))
            return
        fd = libc.inotify_init1(_IN_NONBLOCK | _IN_CLOEXEC)
        if fd < 0:
            log.debug("inotify unavailable (%s): stat per query", os.strerror(ctypes.get_errno()))
            return
        for f in folders:
            if libc.inotify_add_watch(fd, os.fsencode(f), _MASK) < 0:
                log.debug("cannot watch %s (%s): stat per query", f,
                          os.strerror(ctypes.get_errno()))
                os.close(fd)
                return
        self._fd = fd
        self._pid = os.getpid()  # a forked child must not drain its parent's events
        self._finalizer = weakref.finalize(self, os.close, fd)

    @property
    def active(self) -> bool:
        return self._fd is not None

    def generation(self) -> int | None:
        """A number that changes whenever a watched file may have changed (events, or
        :data:`REFRESH_S` passed); ``None`` without a watch: check every time."""
        if self._fd is None or os.getpid() != self._pid:
            return None
        with self._lock:
            changed = False
            try:
                # bytes queued first: no exception raised and caught on the common empty
                # queue (the drain took 37 us of a posterior query, right after the scans)
                while _queued(self._fd):
                    os.read(self._fd, 65536)  # every queued event (overflow included)
                    changed = True
            except BlockingIOError:
                pass
            except OSError as exc:  # the watch is broken: back to a stat per query
                log.warning("map change notice failed (%s): checking files every query", exc)
                self.close()
                return None
            now = time.monotonic()
            if changed or now - self._since >= REFRESH_S:
                self._generation += 1
                self._since = now
            return self._generation

    def bump(self) -> None:
        """A new generation for the queries that start from now (a file failed its check:
        every file is checked again, and memos kept per generation are dropped)."""
        with self._lock:
            self._generation += 1

    @contextlib.contextmanager
    def query(self) -> Iterator[None]:
        """One drain for the checks of a whole query on this thread (:meth:`current`)."""
        outer = getattr(self._local, "gen", _OUTSIDE)
        self._local.gen = self.generation()
        try:
            yield
        finally:
            self._local.gen = outer

    def current(self) -> int | None:
        """The generation of this thread's query; outside a query, :meth:`generation`."""
        gen = getattr(self._local, "gen", _OUTSIDE)
        return self.generation() if gen is _OUTSIDE else gen

    def close(self) -> None:
        if self._fd is not None:
            self._fd = None
            self._finalizer()
