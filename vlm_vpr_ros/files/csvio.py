"""CSV tables in and out: one place for "file missing / columns missing" errors and atomic
writes.

Readers are strict where a lenient parse would silently change a value: numbers are plain
ASCII decimals (``float()`` alone would read ``3_9.5591`` as 39.5591 and ``٣`` as 3), a
column name given twice is refused (``csv.DictReader`` would keep the last one), and a NUL byte
anywhere in the file (not only in its first 64 KiB) is "malformed CSV" naming its line."""

from __future__ import annotations

import contextlib
import csv
import logging
import math
import os
import re
from pathlib import Path
from typing import Any, Iterable, Iterator

from vlm_vpr_ros.errors import DataError
from vlm_vpr_ros.files.atomic import atomic_path

log = logging.getLogger(__name__)


def read_rows(path: str | os.PathLike[str], what: str = "CSV",
              required: Iterable[str] = ()) -> tuple[list[str], list[tuple[int, dict[str, str]]]]:
    """``(columns, [(line number, row), ...])`` of a UTF-8 CSV (a BOM, as Excel writes it, is
    accepted; header names are stripped). DataError when the file, a required column or the
    CSV syntax is wrong."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{what} not found: {path}")
    try:
        line = _nul_line(path)
        if line is not None:
            raise DataError(f"{path}:{line}: malformed CSV: a NUL byte (a binary file or a "
                            "corrupt line, not a CSV)")
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            cols = [(c or "").strip() for c in reader.fieldnames or []]
            reader.fieldnames = cols
            _check_unique_columns(path, cols)
            missing = set(required) - set(cols)
            if missing:
                raise DataError(f"{path}: missing column(s) {sorted(missing)}; has {cols}")
            rows = []
            for row in reader:
                rows.append((reader.line_num, row))
            return cols, rows
    except (csv.Error, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: malformed CSV: {exc}") from None
    except OSError as exc:
        raise DataError(f"cannot read {what} {path}: {exc.strerror or exc}") from None


@contextlib.contextmanager
def stream_rows(path: str | os.PathLike[str], what: str = "CSV", required: Iterable[str] = ()
                ) -> Iterator[tuple[list[str], Iterator[tuple[int, list[str]]]]]:
    """``with stream_rows(path) as (columns, rows):`` the rows as ``(line, [values])`` read one
    at a time (constant memory: for files of millions of rows), with the checks of
    :func:`read_rows` (header, required and repeated columns, NUL bytes, CSV syntax: a
    DataError naming the file and line)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{what} not found: {path}")
    try:
        line = _nul_line(path)  # one fast pass (C find): the csv module accepts NUL bytes
        fh = path.open(newline="", encoding="utf-8-sig")
    except OSError as exc:
        raise DataError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    if line is not None:
        fh.close()
        raise DataError(f"{path}:{line}: malformed CSV: a NUL byte (a binary file or a "
                        "corrupt line, not a CSV)")
    with fh:
        reader = csv.reader(fh)

        def fail(exc: Exception) -> DataError:
            if isinstance(exc, OSError):
                return DataError(f"cannot read {what} {path}: {exc.strerror or exc}")
            return DataError(f"{path}:{reader.line_num}: malformed CSV: {exc}")

        try:
            cols = [c.strip() for c in next(reader, [])]
        except (csv.Error, UnicodeDecodeError, OSError) as exc:
            raise fail(exc) from None
        _check_unique_columns(path, cols)
        missing = set(required) - set(cols)
        if missing:
            raise DataError(f"{path}: missing column(s) {sorted(missing)}; has {cols}")

        def rows() -> Iterator[tuple[int, list[str]]]:
            try:
                for row in reader:
                    if row:
                        yield reader.line_num, row
            except (csv.Error, UnicodeDecodeError, OSError) as exc:
                raise fail(exc) from None
        yield cols, rows()


def _nul_line(path: Path) -> int | None:
    """Line number of the first NUL byte (None when there is none); reads 1 MiB at a time."""
    line = 1
    with path.open("rb") as raw:
        while chunk := raw.read(1 << 20):
            i = chunk.find(b"\x00")
            if i >= 0:
                return line + chunk.count(b"\n", 0, i)
            line += chunk.count(b"\n")
    return None


def _check_unique_columns(path: Path, cols: list[str]) -> None:
    first: dict[str, int] = {}
    for k, c in enumerate(cols, 1):
        if c and c in first:
            raise DataError(f"{path}: column {c!r} appears twice in the header (columns "
                            f"{first[c]} and {k}); keep one")
        first.setdefault(c, k)


def read_table(path: str | os.PathLike[str], required: Iterable[str],
               what: str = "CSV") -> list[dict[str, str]]:
    """All rows of a CSV as dicts; DataError when the file or a required column is missing."""
    return [row for _, row in read_rows(path, what, required)[1]]


#: a plain decimal number: digits, one optional point, an optional exponent (ASCII only)
#: a plain ASCII decimal number (what :func:`strict_float` accepts)
NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)


def strict_float(value: object) -> float | None:
    """``value`` as a float when it is a plain decimal number (surrounding spaces allowed),
    else None: no ``_`` separators, no non-ASCII digits, no ``nan``/``inf`` words."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, str) and NUMBER.fullmatch(value.strip()):
        return float(value)
    return None


def parse_number(value: object, where: str, field: str) -> float:
    """A finite number or a DataError naming ``where`` (``file:line``), the field and value."""
    x = strict_float(value)
    if x is None:
        raise DataError(f"{where}: {field} {value!r} is not a number")
    if not math.isfinite(x):
        raise DataError(f"{where}: {field} {value} is out of range")
    return x


def parse_latlon(lat: object, lon: object, where: str) -> tuple[float, float]:
    """Finite WGS-84 degrees or a DataError naming ``where`` (``file:line``) and the value."""
    la, lo = strict_float(lat), strict_float(lon)
    if la is None or lo is None:
        raise DataError(f"{where}: lat/lon not numbers: {lat!r}, {lon!r}")
    if not (math.isfinite(la) and -90.0 <= la <= 90.0):
        raise DataError(f"{where}: latitude {lat} out of range [-90, 90]")
    if not (math.isfinite(lo) and -180.0 <= lo <= 180.0):
        raise DataError(f"{where}: longitude {lon} out of range [-180, 180]")
    return la, lo


def unique_rows(items: Iterable[tuple[int, str, Any]], path: str | os.PathLike[str],
                what: str = "row") -> dict[str, Any]:
    """``{key: value}`` from ``(line, key, value)`` in file order. A key repeated with the same
    value is kept once (warning with the line numbers); with another value it is a DataError
    naming both lines."""
    out: dict[str, Any] = {}
    first: dict[str, int] = {}
    repeats: list[str] = []
    for line, key, value in items:
        if key in out:
            if out[key] != value:
                raise DataError(f"{path}: lines {first[key]} and {line} give different "
                                f"values for {what} {key!r}; keep one")
            repeats.append(f"{key!r} (lines {first[key]}, {line})")
            continue
        out[key], first[key] = value, line
    if repeats:
        log.warning("%s: %d repeated %s row(s) kept once: %s%s", path, len(repeats), what,
                    ", ".join(repeats[:5]), " ..." if len(repeats) > 5 else "")
    return out


def write_csv_atomic(path: str | os.PathLike[str], fieldnames: list[str],
                     rows: Iterable[dict]) -> None:
    """Write a CSV atomically (:func:`~vlm_vpr_ros.files.atomic.atomic_path`)."""
    with atomic_path(path) as tmp, tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=fieldnames, extrasaction="ignore")
        w.writeheader()
        for row in rows:
            w.writerow(row)


def read_file_column(path: str | Path) -> list[str]:
    """The ``file`` column of a queries CSV (other columns are ignored); a CSV without a single
    file name is a DataError (a run over nothing would "succeed" with an empty result)."""
    files = [row["file"] for row in read_table(path, ("file",), "queries CSV") if row["file"]]
    if not files:
        raise DataError(f"{path}: no rows with a file name")
    return files
