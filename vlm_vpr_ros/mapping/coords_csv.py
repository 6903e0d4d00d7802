"""The coordinates CSV of a build (``file, lat, lon``): one reader for every input that names
reference pictures by file (image builds, builds from precomputed descriptors, bags, the demo)."""

from __future__ import annotations

import os

from vlm_vpr_ros.errors import DataError
from vlm_vpr_ros.files.csvio import parse_latlon, read_rows, unique_rows
from vlm_vpr_ros.maps.format import bad_ref_id


def check_reference_id(ref_id: str, where: str) -> str:
    """A reference id is a relative path inside the images folder: no absolute paths, no
    ``..``; anything else is a DataError naming ``where``."""
    if not ref_id or not ref_id.strip():
        raise DataError(f"{where}: empty file name")
    if bad_ref_id(ref_id):
        raise DataError(f"{where}: file {ref_id!r} points outside the images folder (use a "
                        "path relative to it, without '..')")
    return ref_id


def read_coords_csv(path: str | os.PathLike[str]) -> list[tuple[str, float, float]]:
    """Read ``file, lat, lon`` rows; invalid coordinates, file names outside the images folder
    and conflicting repeated rows are DataErrors naming the line."""
    _, rows = read_rows(path, "coordinates CSV", ("file", "lat", "lon"))
    items = []
    for n, row in rows:
        where = f"{path}:{n}"
        items.append((n, check_reference_id(row["file"] or "", where),
                      parse_latlon(row["lat"], row["lon"], where)))
    table = unique_rows(items, path, "file")
    if not table:
        raise DataError(f"{path}: no rows")
    return [(f, la, lo) for f, (la, lo) in table.items()]
