"""One writer at a time per output folder: the lock every command that writes a map (or a bag,
an evaluation, a descriptor shard folder) takes before it touches it.

The lock is ``flock`` on ``PARENT/.NAME.lock``, a small file *beside* the folder, never inside
it: a build swaps the whole folder (``os.replace``) and an edit rewrites files inside it, so a
lock inside the folder would move away with the old folder and the two would not exclude each
other (the data-loss race of issue 19). The file exists only while the lock is held (it names
the holder: pid, command, start time, shown to a process that is refused): the holder deletes it
before it lets go, and a process that gets the ``flock`` checks that the path still names the
file it locked (else it locked a deleted file and starts over), so two processes never both hold
it. A ``kill -9`` leaves the file behind, unlocked: the next writer takes it over.

A second writer waits up to :data:`WAIT_S` seconds (environment ``VLM_VPR_LOCK_WAIT_S``; 0 =
refuse at once), then is refused with one line. ``flock`` locks are released by the kernel when
the holder dies (Ctrl-C, ``kill -9``), so a crash never leaves a map locked.

When the parent folder cannot hold a lock file (read-only, owned by another user) the lock falls
back to ``NAME/.edit.lock`` inside the folder, only for in-place edits (``inside_ok``): a build
could not swap that folder either, since renaming it needs the same write permission.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import time
from pathlib import Path
from typing import IO

from vlm_vpr_ros.errors import OutputError

log = logging.getLogger(__name__)

#: seconds a second writer waits for the lock before it is refused
WAIT_S = 10.0
_POLL_S = 0.1


def wait_s() -> float:
    """The wait of this process: ``VLM_VPR_LOCK_WAIT_S`` when set (finite, >= 0), else
    :data:`WAIT_S`."""
    raw = os.environ.get("VLM_VPR_LOCK_WAIT_S")
    if raw is None or not raw.strip():
        return WAIT_S
    try:
        value = float(raw)
    except ValueError:
        value = -1.0
    if not 0.0 <= value < 1e7:
        raise OutputError(f"VLM_VPR_LOCK_WAIT_S must be seconds >= 0, got {raw!r}")
    return value


def lock_path(target: str | os.PathLike[str]) -> Path:
    """``PARENT/.NAME.lock`` for ``target``, with symbolic links of the parent resolved (two
    spellings of one folder take one lock)."""
    t = Path(os.path.abspath(target))
    if not t.name or t.name in (".", ".."):
        raise OutputError(f"{target}: not a usable folder name")
    return Path(os.path.realpath(t.parent)) / f".{t.name}.lock"


def _holder_line(what: str) -> str:
    return f"pid {os.getpid()}, {what}, since {time.strftime('%Y-%m-%d %H:%M:%S')}"


class WriterLock:
    """``with WriterLock(target, "write"):`` — exclusive writer lock of ``target`` (a folder
    that may not exist yet). Raises :class:`OutputError` (one line) when another process holds
    it for longer than the wait."""

    def __init__(self, target: str | os.PathLike[str], what: str = "a writer",
                 inside_ok: bool = False, wait: float | None = None) -> None:
        """``what``: the operation, named to a writer that is refused (e.g. "map add")."""
        self.target = Path(target)
        self.what = what
        self.path = lock_path(target)
        self.inside_ok = inside_ok
        self.wait = wait_s() if wait is None else float(wait)
        self._fh: IO[str] | None = None

    def _open(self) -> IO[str]:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)  # a new output's parent
            return open(self.path, "a+", encoding="utf-8")
        except OSError as exc:
            inside = self.target / ".edit.lock"
            if self.inside_ok and exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS) \
                    and self.target.is_dir():
                log.debug("cannot create %s (%s): locking %s instead", self.path,
                          exc.strerror, inside)
                self.path = inside
                return open(inside, "a+", encoding="utf-8")
            raise OutputError(f"cannot lock {self.target}: cannot create {self.path} "
                              f"({exc.strerror}); choose a folder you can write to") from None

    def holder(self) -> str:
        """The line the current holder wrote ('' when unknown)."""
        try:
            return self.path.read_text(encoding="utf-8", errors="replace").strip()[:200]
        except OSError:
            return ""

    def acquire(self) -> "WriterLock":
        deadline = time.monotonic() + self.wait
        told = False
        while True:
            fh = self._open()
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                fh.close()
                if time.monotonic() >= deadline:
                    who = self.holder()
                    raise OutputError(
                        f"{self.target} is being written by another process"
                        f"{f' ({who})' if who else ''}; try again when it has finished "
                        f"(lock {self.path})") from None
                if not told:
                    log.info("waiting up to %.0f s for %s: another process is writing it (%s)",
                             self.wait, self.target, self.holder() or "unknown")
                    told = True
                time.sleep(_POLL_S)
                continue
            except OSError as exc:
                fh.close()
                raise OutputError(f"cannot lock {self.target}: {exc.strerror}") from None
            if self._still_linked(fh):
                break
            fh.close()  # the holder deleted it while we waited: lock the new file
        try:  # who holds it, for the message of a refused writer (best effort)
            fh.seek(0)
            fh.truncate()
            fh.write(_holder_line(self.what) + "\n")
            fh.flush()
        except OSError:
            pass
        self._fh = fh
        return self

    def _still_linked(self, fh: IO[str]) -> bool:
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return False
        mine = os.fstat(fh.fileno())
        return (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino)

    def release(self) -> None:
        if self._fh is not None:
            try:
                self.path.unlink()  # while still locked: see the module docstring
            except OSError:
                pass
            self._fh.close()  # closing the descriptor releases the flock
            self._fh = None

    @property
    def held(self) -> bool:
        return self._fh is not None

    def __enter__(self) -> "WriterLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
