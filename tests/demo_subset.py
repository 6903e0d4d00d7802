"""The first ``n`` shipped demo images as a coordinates CSV, for tests that build a small map."""

from __future__ import annotations

import csv
from pathlib import Path


def demo_coords(demo_data: Path, folder: Path, n: int) -> tuple[list[dict[str, str]], Path]:
    """(the first ``n`` rows of the demo's coords.csv, the CSV of them written in ``folder``)."""
    rows = list(csv.DictReader(open(demo_data / "coords.csv")))[:n]
    path = folder / "coords.csv"
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["file", "lat", "lon"], extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return rows, path
