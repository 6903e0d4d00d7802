"""Memory-mapped arrays of a map folder: loading a ``.npy`` as a read-only mapping of the
expected shape (one that keeps no file descriptor open), the ids as a sequence of str over
their fixed-width bytes, read-ahead advice for scattered rows (used by :mod:`.store`,
:mod:`.features` and the descriptor builder), and anonymous huge-page memory for the arrays a
query scans whole (:mod:`.search`'s pool)."""

from __future__ import annotations

import ctypes
import functools
import math
import mmap
import os
import weakref
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.libc import libc


#: a transparent huge page on x86-64 (and the alignment that lets the kernel use them)
HUGE_PAGE_BYTES = 2 * 2 ** 20


class IdView:
    """Read-only sequence of str over a memory-mapped fixed-width UTF-8 array."""

    def __init__(self, raw: np.ndarray) -> None:
        self._raw = raw

    def __len__(self) -> int:
        return len(self._raw)

    def __getitem__(self, i: int) -> str:
        return self._raw.item(i).decode("utf-8", errors="replace")  # bytes, NULs stripped

    def take(self, rows: Any) -> list[str]:
        """The ids of these rows (one read of the mapped array)."""
        return [b.decode("utf-8", errors="replace") for b in self._raw[rows].tolist()]

    def __iter__(self) -> Iterator[str]:
        for start in range(0, len(self._raw), 65536):
            for b in self._raw[start:start + 65536].tolist():
                yield b.decode("utf-8", errors="replace")


def load_array(root: Path, rel: str, shape: tuple[int, ...], kind: str) -> np.ndarray:
    """A memory-mapped ``.npy`` of the expected shape and dtype kind (:func:`map_npy`; rows
    are read a few at a time, so without read-ahead: otherwise every query maps ~32 pages per
    row and the file-backed RSS grows towards the whole file)."""
    try:
        arr = map_npy(root / rel, random_access=True)
    except (OSError, ValueError) as exc:
        raise MapError(f"{root}: cannot read {rel}: {exc}") from exc
    ok = arr.shape == shape and (arr.dtype.kind == "S" if kind == "S"
                                 else arr.dtype == np.dtype(kind))
    if not ok:
        raise MapError(f"{root}: {rel} is {arr.dtype}{arr.shape}, expected {kind}{shape}")
    return arr


@functools.lru_cache(maxsize=1)
def _libc() -> Any:
    """The C library with ``mmap``, ``munmap`` and ``madvise`` declared; None where they cannot
    be reached (then :func:`map_npy` uses numpy's own mapping)."""
    lib = libc()
    if lib is None or not all(hasattr(lib, f) for f in ("mmap", "munmap", "madvise")):
        return None
    lib.mmap.restype = ctypes.c_void_p
    lib.mmap.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int,
                         ctypes.c_int, ctypes.c_long)
    lib.munmap.argtypes = (ctypes.c_void_p, ctypes.c_size_t)
    lib.madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
    return lib


def _npy_header(fh: Any) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, Fortran order, dtype) of the ``.npy`` open in ``fh``, which is left at the
    data (numpy's own header readers; versions 1.0 and 2.0, what ``np.save`` writes unless
    a structured dtype has non-ASCII field names)."""
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(fh)
    if version == (2, 0):
        return np.lib.format.read_array_header_2_0(fh)
    raise ValueError(f"unsupported .npy format version {version[0]}.{version[1]}")


def map_npy(path: Path | str, random_access: bool = False) -> np.ndarray:
    """The data of the ``.npy`` at ``path`` as a read-only memory mapping that keeps no file
    descriptor open (the kernel keeps the mapped file alive, also after it is replaced or
    deleted); unmapped when the last view of it is gone. ``random_access``: advise the
    kernel not to read ahead (``MADV_RANDOM``). Object arrays are refused (no pickle).

    Why by hand: ``np.load(mmap_mode="r")`` maps through Python's ``mmap``, which keeps a
    duplicate of the descriptor for the mapping's life (before Python 3.13's ``trackfd``).
    A map keeps two to six files of each opened submap mapped (ids, coordinates, re-rank
    vectors, local features), so a planet map of a few hundred submaps reached the common
    soft limit of 1,024 descriptors: measured here, a 166-submap 4.1M pq map held 496 after
    one global query, and under a limit of 300 every such query failed with ``EMFILE``, as
    did every other file or socket the process then tried to open."""
    with open(path, "rb") as fh:
        shape, fortran, dtype = _npy_header(fh)
        if dtype.hasobject:
            raise ValueError("an object array (pickled data) is not read")
        offset, size = fh.tell(), os.fstat(fh.fileno()).st_size
        count = math.prod(shape)
        if size < offset + count * dtype.itemsize:
            raise ValueError(f"truncated: {size - offset} bytes of data, the header needs "
                             f"{count * dtype.itemsize}")
        libc = _libc()
        if libc is None:  # numpy's mapping (it keeps a descriptor)
            arr = np.load(path, mmap_mode="r", allow_pickle=False).view(np.ndarray)
            mm = getattr(arr.base, "_mmap", None)
            if random_access and mm is not None and hasattr(mmap, "MADV_RANDOM"):
                mm.madvise(mmap.MADV_RANDOM)
            return arr
        addr = libc.mmap(None, size, mmap.PROT_READ, mmap.MAP_SHARED, fh.fileno(), 0)
        if addr is None or addr == ctypes.c_void_p(-1).value:  # MAP_FAILED
            err = ctypes.get_errno()
            raise OSError(err, f"cannot map {path}: {os.strerror(err)}")
    if random_access and hasattr(mmap, "MADV_RANDOM"):
        libc.madvise(addr, size, mmap.MADV_RANDOM)  # advice: its failure changes nothing
    buf = (ctypes.c_ubyte * size).from_address(addr)
    weakref.finalize(buf, libc.munmap, addr, size).atexit = False  # exit unmaps anyway
    arr = np.frombuffer(memoryview(buf).toreadonly(), dtype, count, offset)
    return arr.reshape(shape, order="F" if fortran else "C")


def prefetch_rows(path: Path | str, row_bytes: int, rows: np.ndarray, offset: int) -> None:
    """Ask the kernel to read rows ``rows`` (``row_bytes`` each, data at ``offset``) of the file
    at ``path`` now: ``posix_fadvise(WILLNEED)`` per row queues the reads without waiting, so a
    cold query then waits for about one round of disk reads, not one read per page fault in
    turn (measured here: 0.06 ms instead of 0.8 ms per cold row). Advice only: never fails."""
    if not len(rows) or not hasattr(os, "posix_fadvise"):
        return
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return  # the read itself reports a missing file
    try:
        for r in np.unique(np.asarray(rows, dtype=np.int64)).tolist():
            os.posix_fadvise(fd, offset + r * row_bytes, row_bytes, os.POSIX_FADV_WILLNEED)
    except OSError:
        pass
    finally:
        os.close(fd)


def npy_data_offset(path: Path, arr: np.ndarray) -> int:
    """Where the data of a ``.npy`` this package wrote starts (header first, data to the end;
    sizes are checked against the manifest before any read)."""
    return os.stat(path).st_size - arr.nbytes


def huge_page_array(shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """A zeroed array in anonymous memory that starts on a 2 MiB boundary and is advised for
    transparent huge pages (``MADV_HUGEPAGE``); below one huge page, off Linux, or where the
    kernel has no THP or ignores the advice (THP ``never``), ordinary memory, same contents.

    Why by hand: a scan of 512-D float32 rows crosses a 4 KiB page every two rows, and with
    4 KiB pages the TLB misses cost about as much as the arithmetic. Measured on an AVX-512
    EPYC (issue 31, THP ``madvise``, the kernel's default on Debian and Ubuntu): FAISS's exact
    scan of 24k rows 82 ns a row here against 120 in an index's own heap copy, which the
    kernel backs with 4 KiB pages. numpy advises its own large arrays the same way, but only
    while its global switch is on and without the alignment; this helper does not depend on
    either."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if nbytes < HUGE_PAGE_BYTES or not hasattr(mmap, "MADV_HUGEPAGE"):
        return np.zeros(shape, dtype)
    # private: an anonymous *shared* mapping (Python's default) is shmem, which has its own
    # huge-page setting (``shmem_enabled``, off by default)
    buf = mmap.mmap(-1, nbytes + HUGE_PAGE_BYTES, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    raw = np.frombuffer(buf, np.uint8)  # keeps ``buf`` alive as long as any view of it
    start = (-raw.ctypes.data) % HUGE_PAGE_BYTES  # a multiple of the 4 KiB page size
    try:
        buf.madvise(mmap.MADV_HUGEPAGE, start, nbytes)
    except OSError:
        pass  # THP off or unsupported: 4 KiB pages, same contents
    return raw[start:start + nbytes].view(dtype).reshape(shape)
