"""CSV tables in and out: one place for "file missing / columns missing" errors and atomic
writes."""

from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import Iterable

from vlm_vpr_ros.errors import DataError


def read_table(path: str | os.PathLike[str], required: Iterable[str],
               what: str = "CSV") -> list[dict[str, str]]:
    """All rows of a CSV as dicts; DataError when the file or a required column is missing."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{what} not found: {path}")
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            missing = set(required) - set(reader.fieldnames or [])
            if missing:
                raise DataError(f"{path}: missing column(s) {sorted(missing)}; "
                                f"has {reader.fieldnames}")
            return list(reader)
    except (csv.Error, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: malformed CSV: {exc}") from None


def write_csv_atomic(path: str | os.PathLike[str], fieldnames: list[str],
                     rows: Iterable[dict]) -> None:
    """Write a CSV through a temporary file and ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=fieldnames, extrasaction="ignore")
        w.writeheader()
        for row in rows:
            w.writerow(row)
    os.replace(tmp, path)
