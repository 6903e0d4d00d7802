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

A lock file that exists but is not writable for this user (another user's writer holds it) is
opened read-only: ``flock`` works on a read-only descriptor, so users share one lock.

A lock file is never reached through a symbolic link: every open is ``O_NOFOLLOW`` (a link at
the lock's name, to a user's file or dangling, is refused with one line naming it, so the
holder line is never written into another file and no file is created at the link's target),
the holder line shown to a refused writer is read the same way, and the holder deletes the
name only while it still is the very file it locked (``lstat``: a link never matches).
The core is ``flock`` plus these few checks; the ``filelock`` library (installed with ray) was
weighed: its Unix lock keeps the file in place after release and would need the same guards
around it for symbolic links and the holder line, so it would not make this smaller.

In-place edits (``inside_ok``) also lock ``NAME/.edit.lock`` inside the folder, after the lock
beside it; a build's swap locks it too (:func:`inside_lock`). A user who cannot create the lock
beside the folder (its parent is read-only for them, and no lock file is there) locks only the
inside one: every other edit and every swap of that folder takes it as well, so the two never
run together. A build could not swap that folder for them either (renaming it needs the same
write permission).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import stat
import time
from pathlib import Path
from typing import IO, Iterator

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


_NO_WRITE = (errno.EACCES, errno.EPERM, errno.EROFS)
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_sys_open = os.open  # every open of a lock file (one name: tests simulate permissions on it)


class _Flock:
    """One ``flock``-ed lock file: created when missing, deleted by its holder before it lets
    go (see the module docstring)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fh: IO[str] | None = None

    def _refuse_link(self) -> None:
        if os.path.islink(self.path):
            raise OutputError(f"lock file {self.path} is a symbolic link (not made by vlm-vpr; "
                              "it is never followed): remove it and try again")

    def _open(self) -> IO[str]:
        try:
            fd = _sys_open(self.path, os.O_RDWR | os.O_CREAT | os.O_APPEND | _NOFOLLOW, 0o644)
            return os.fdopen(fd, "a+", encoding="utf-8")
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                self._refuse_link()
            if exc.errno not in _NO_WRITE or not self.path.is_file():
                self._refuse_link()
                raise
            fd = _sys_open(self.path, os.O_RDONLY | _NOFOLLOW)  # flock works read-only too
            return os.fdopen(fd, "r", encoding="utf-8")

    def try_lock(self, what: str) -> bool:
        """One attempt (OSError when the file cannot be opened at all)."""
        while True:
            fh = self._open()
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                fh.close()
                return False
            except OSError:
                fh.close()
                raise
            if self._linked(fh):
                break
            fh.close()  # the holder deleted it while we waited: lock the new file
        try:  # who holds it, for the message of a refused writer (best effort)
            fh.seek(0)
            fh.truncate()
            fh.write(_holder_line(what) + "\n")
            fh.flush()
        except OSError:  # a read-only descriptor (io.UnsupportedOperation is an OSError)
            pass
        self.fh = fh
        return True

    def _linked(self, fh: IO[str]) -> bool:
        try:
            st = os.lstat(self.path)  # a symbolic link put at the name never matches
        except FileNotFoundError:
            return False
        mine = os.fstat(fh.fileno())
        return (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino)

    def holder(self) -> str:
        try:
            fd = _sys_open(self.path, os.O_RDONLY | _NOFOLLOW | getattr(os, "O_NONBLOCK", 0))
        except OSError:
            return ""
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                return ""
            return os.read(fd, 400).decode("utf-8", "replace").strip()[:200]
        except OSError:
            return ""
        finally:
            os.close(fd)

    def release(self) -> None:
        if self.fh is not None:
            if self._linked(self.fh):  # never another holder's file (a swapped folder)
                try:
                    self.path.unlink()  # while still locked: see the module docstring
                except OSError:
                    pass
            self.fh.close()  # closing the descriptor releases the flock
            self.fh = None


class WriterLock:
    """``with WriterLock(target, "write"):`` — exclusive writer lock of ``target`` (a folder
    that may not exist yet). Raises :class:`OutputError` (one line) when another process holds
    it for longer than the wait."""

    def __init__(self, target: str | os.PathLike[str], what: str = "a writer",
                 inside_ok: bool = False, wait: float | None = None) -> None:
        """``what``: the operation, named to a writer that is refused (e.g. "map add");
        ``inside_ok``: an in-place edit (also locks ``target/.edit.lock``)."""
        self.target = Path(target)
        self.what = what
        self.path = lock_path(target)
        self.inside_ok = inside_ok
        self.wait = wait_s() if wait is None else float(wait)
        self._held: list[_Flock] = []
        #: lock ``target/.edit.lock`` only (:func:`inside_lock`)
        self.inside_only = False

    def _parts(self) -> list[_Flock]:
        """The lock files to take, in order (the first one is :attr:`path`)."""
        if self.inside_only:
            self.path = self.target / ".edit.lock"
            return [_Flock(self.path)] if self.target.is_dir() else []
        outer = _Flock(self.path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)  # a new output's parent
            outer._open().close()
        except OutputError:
            raise
        except OSError as exc:
            if not (self.inside_ok and exc.errno in _NO_WRITE and self.target.is_dir()
                    and not os.path.lexists(self.path)):
                raise OutputError(f"cannot lock {self.target}: cannot create {self.path} "
                                  f"({exc.strerror}); choose a folder you can write to"
                                  ) from None
            log.debug("cannot create %s (%s): locking %s only", self.path, exc.strerror,
                      self.target / ".edit.lock")
            self.path = self.target / ".edit.lock"
            return [_Flock(self.path)]
        if self.inside_ok and self.target.is_dir():
            return [outer, _Flock(self.target / ".edit.lock")]
        return [outer]

    def holder(self) -> str:
        """The line the current holder wrote ('' when unknown)."""
        return _Flock(self.path).holder()

    def acquire(self) -> "WriterLock":
        deadline = time.monotonic() + self.wait
        parts = self._parts()
        told = False
        try:
            for k, part in enumerate(parts):
                while not self._try(part, k):
                    if time.monotonic() >= deadline:
                        who = part.holder()
                        raise OutputError(
                            f"{self.target} is being written by another process"
                            f"{f' ({who})' if who else ''}; try again when it has finished "
                            f"(lock {part.path})")
                    if not told:
                        log.info("waiting up to %.0f s for %s: another process is writing it "
                                 "(%s)", self.wait, self.target, part.holder() or "unknown")
                        told = True
                    time.sleep(_POLL_S)
        except BaseException:
            self.release()
            raise
        return self

    def _try(self, part: _Flock, k: int) -> bool:
        try:
            ok = part.try_lock(self.what)
        except OutputError:
            raise
        except OSError as exc:
            if (k > 0 or self.inside_only) and exc.errno in _NO_WRITE:
                return True  # the folder is read-only for us: no edit of ours to exclude
            raise OutputError(f"cannot lock {self.target}: {part.path}: {exc.strerror}"
                              ) from None
        if ok:
            self._held.append(part)
        return ok

    def release(self) -> None:
        while self._held:
            self._held.pop().release()

    @property
    def held(self) -> bool:
        return bool(self._held)

    def __enter__(self) -> "WriterLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


@contextlib.contextmanager
def inside_lock(target: Path, what: str, wait: float | None = None) -> Iterator[None]:
    """``target/.edit.lock`` while a build swaps ``target`` out (an edit of it by a user who
    could not lock beside it holds that one): waits like :class:`WriterLock`. Nothing to lock
    when ``target`` is not a folder or is read-only for us (no one else can edit it then)."""
    lock = WriterLock(target, what, wait=wait)
    lock.inside_only = True
    with lock:
        yield
