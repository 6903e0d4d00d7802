"""The one way this package writes a file, and the one way it hashes one.

Every file (map files, manifests, CSVs, plots, bag metadata, cache entries, weights) is written
to a temporary name in the target's folder (``.NAME.tmp<pid>.<n>``), flushed and ``fsync``-ed,
then moved over the target with ``os.replace`` and the folder entry ``fsync``-ed: a reader sees
the old file or the new one, never a half-written one, and after a crash or power loss the new
file is either complete on disk or absent. On an OS error (disk full, no permission) the
temporary file is removed and :class:`~vlm_vpr_ros.errors.OutputError` says what happened in one
line; any other exception (Ctrl-C included) also removes it and propagates.

:func:`atomic_path` is the primitive (for writers that want a file name: FAISS, matplotlib,
torch); the others write bytes, text, JSON and arrays through it. Folders that are built whole
(maps, bags) use :class:`~vlm_vpr_ros.files.outputs.StagedOutput` on top of this.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import io
import itertools
import json
import os
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from vlm_vpr_ros.errors import OutputError

_counter = itertools.count()


def describe_os_error(exc: OSError, path: str | os.PathLike[str] | None = None) -> str:
    """One line for a write failure, with a hint for the two common causes."""
    where = path or exc.filename or "output"
    why = exc.strerror or str(exc)
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"cannot write {where}: {why} (free some space and run the same command again)"
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return f"cannot write {where}: {why} (choose a folder you can write to)"
    return f"cannot write {where}: {why}"


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (best effort: some file systems refuse it)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def fsync_tree(folder: str | os.PathLike[str], files: bool = True) -> None:
    """Make a folder written by another library durable before it is renamed into place (a bag
    written by rosbags): ``fsync`` every file under it (unless ``files`` is False), then each
    folder."""
    folder = Path(folder)
    if files:
        for path in folder.rglob("*"):
            if path.is_file() and not path.is_symlink():
                with open(path, "rb+") as fh:
                    os.fsync(fh.fileno())
    for sub in [p for p in folder.rglob("*") if p.is_dir()] if files else []:
        _fsync_dir(sub)
    _fsync_dir(folder)


def commit_temp(tmp: Path, path: Path) -> None:
    """Make a finished temporary file durable and move it over ``path`` (the last step of
    :func:`atomic_path`; also for files staged by hand, e.g. a download checked before use)."""
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    _fsync_dir(Path(path).parent)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path next to ``path``; when the block ends without an exception the
    file written there is fsync-ed and moved over ``path``. ``suffix`` keeps an extension some
    writers insist on (matplotlib picks the format from it)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.{next(_counter)}{suffix}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if os.path.lexists(tmp):  # never write through a link (or file) left at our name
            os.unlink(tmp)
        yield tmp
        commit_temp(tmp, path)
    except OutputError:
        tmp.unlink(missing_ok=True)
        raise
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(describe_os_error(exc, path)) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)


def atomic_write_text(path: str | os.PathLike[str], text: str, newline: str | None = None
                      ) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline=newline) as fh:
        fh.write(text)


def atomic_write_json(path: str | os.PathLike[str], obj: Any, indent: int | None = 2,
                      ensure_ascii: bool = True) -> None:
    atomic_write_text(path, json.dumps(obj, indent=indent, ensure_ascii=ensure_ascii) + "\n")


def atomic_save_npy(path: str | os.PathLike[str], arr: np.ndarray) -> None:
    """``np.save`` streamed into the temporary file (no in-memory copy of a large array)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, np.ascontiguousarray(arr), allow_pickle=False)


def atomic_save_npz(path: str | os.PathLike[str], arrays: Mapping[str, np.ndarray]) -> None:
    buf = io.BytesIO()
    np.savez(buf, **{k: np.ascontiguousarray(v) for k, v in arrays.items()})
    atomic_write_bytes(path, buf.getvalue())


def atomic_write_index(path: str | os.PathLike[str], index: Any) -> None:
    """A FAISS index, written by FAISS itself into the temporary file."""
    import faiss

    with atomic_path(path) as tmp:
        faiss.write_index(index, str(tmp))


def file_sha256(path: str | os.PathLike[str]) -> str:
    """Hex sha256 of a file's bytes (``hashlib.file_digest``: streamed, no Python loop)."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()
