"""CSV tables in and out: one place for "file missing / columns missing" errors and atomic
writes."""

from __future__ import annotations

import csv
import logging
import math
import os
from pathlib import Path
from typing import Any, Iterable

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
        with path.open("rb") as raw:
            if b"\x00" in raw.read(1 << 16):
                raise DataError(f"{path}: malformed CSV: NUL bytes (a binary file, not a CSV)")
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            cols = [(c or "").strip() for c in reader.fieldnames or []]
            reader.fieldnames = cols
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


def read_table(path: str | os.PathLike[str], required: Iterable[str],
               what: str = "CSV") -> list[dict[str, str]]:
    """All rows of a CSV as dicts; DataError when the file or a required column is missing."""
    return [row for _, row in read_rows(path, what, required)[1]]


def parse_latlon(lat: object, lon: object, where: str) -> tuple[float, float]:
    """Finite WGS-84 degrees or a DataError naming ``where`` (``file:line``) and the value."""
    try:
        la, lo = float(lat), float(lon)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise DataError(f"{where}: lat/lon not numbers: {lat!r}, {lon!r}") from None
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
    """The ``file`` column of a queries CSV (other columns are ignored)."""
    return [row["file"] for row in read_table(path, ("file",), "queries CSV") if row["file"]]
