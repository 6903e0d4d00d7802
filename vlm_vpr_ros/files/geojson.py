"""Localization results as GeoJSON (RFC 7946) for a GIS: ``vlm-vpr evaluate --geojson OUT``.

One ``Feature`` per row of a results CSV, in the CSV's order, in a ``FeatureCollection``:

* ``geometry``: a ``Point`` at the estimate, coordinates ``[longitude, latitude]`` (RFC 7946
  §3.1.1: longitude first, WGS 84 degrees, no ``crs`` member), rounded to 7 decimals (1 cm);
  ``null`` when the row has no valid estimate (no match, a failed query): RFC 7946 §3.2 allows
  a feature without geometry, and the row is not dropped (its ``flags`` say why).
* ``properties``: ``file``, ``ref_id``, ``status``, ``flags`` (a list; ``|``-separated in the
  CSV), ``uncertainty_m``, ``radius95_m``, ``p_correct``, ``confidence`` (numbers, or null
  where the CSV cell is empty or not a number) and, with ground truth, ``truth``
  (``[longitude, latitude]``) and ``error_km`` (great-circle, :mod:`vlm_vpr_ros.geodesy`).

The file is written atomically (:mod:`vlm_vpr_ros.files.atomic`), after the one check of
every output (:func:`~vlm_vpr_ros.files.outputs.check_file_output`): never over an input or a
file of the user's; a GeoJSON of ours (its ``generator`` member, a foreign member RFC 7946 §6.1
allows) is replaced.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any, Mapping, Sequence

from vlm_vpr_ros.files.atomic import atomic_write_json
from vlm_vpr_ros.files.csvio import read_table, strict_float
from vlm_vpr_ros.geodesy import haversine_km, valid_latlon

#: numeric properties copied from the results CSV
NUMBERS = ("uncertainty_m", "radius95_m", "p_correct", "confidence")
DIGITS = 7  # 1e-7 degree: about 1 cm
GENERATOR = "vlm_vpr_ros evaluate --geojson"
_OURS = re.compile(r'\A\{\s*"type":\s*"FeatureCollection",\s*"generator":\s*"'
                   + re.escape(GENERATOR) + '"')


def is_results_geojson(path: Path) -> bool:
    """Whether ``path`` is a GeoJSON this command wrote (its head names our generator)."""
    try:
        with open(path, encoding="utf-8") as fh:
            return bool(_OURS.match(fh.read(256)))
    except (OSError, UnicodeDecodeError):
        return False


def _number(value: object) -> float | None:
    x = strict_float(value)
    return x if x is not None and math.isfinite(x) else None


def _position(lat: object, lon: object) -> list[float] | None:
    """``[lon, lat]`` (RFC 7946 order), or None for a missing or invalid position."""
    la, lo = _number(lat), _number(lon)
    if la is None or lo is None or not valid_latlon(la, lo):
        return None
    return [round(lo, DIGITS), round(la, DIGITS)]


def result_feature(row: Mapping[str, Any],
                   truth: tuple[float, float] | None = None) -> dict[str, Any]:
    """The Feature of one results row (``truth``: its ground truth as (lat, lon))."""
    point = _position(row.get("lat"), row.get("lon"))
    flags = [f.strip() for f in str(row.get("flags") or "").split("|") if f.strip()]
    props: dict[str, Any] = {"file": row.get("file", ""), "ref_id": row.get("ref_id") or "",
                             "status": row.get("status") or "", "flags": flags}
    props.update({k: _number(row.get(k)) for k in NUMBERS})
    if truth is not None:
        props["truth"] = _position(*truth)
        props["error_km"] = (None if point is None or props["truth"] is None else
                             round(float(haversine_km(point[1], point[0], truth[0],
                                                      truth[1])), 6))
    return {"type": "Feature",
            "geometry": None if point is None else {"type": "Point", "coordinates": point},
            "properties": props}


def results_collection(rows: Sequence[Mapping[str, Any]],
                       truth: Mapping[str, tuple[float, float]] | None = None
                       ) -> dict[str, Any]:
    """A FeatureCollection of the rows (with ``truth``: file -> (lat, lon))."""
    return {"type": "FeatureCollection", "generator": GENERATOR,
            "features": [result_feature(r, None if truth is None else truth.get(r.get("file")))
                         for r in rows]}


def write_results_geojson(results_csv: str | os.PathLike[str], path: str | os.PathLike[str],
                          truth: Mapping[str, tuple[float, float]] | None = None) -> int:
    """Write the results CSV's rows as GeoJSON to ``path``; returns how many rows have a point.
    A missing file or column is a DataError naming it (:func:`read_table`)."""
    doc = results_collection(read_table(results_csv, ("file", "lat", "lon"), "results CSV"),
                             truth)
    atomic_write_json(path, doc)
    return sum(f["geometry"] is not None for f in doc["features"])
