"""Accuracy summaries shared by ``vlm-vpr evaluate``, ``evaluate-bag``, ``priors score`` and the
demo: one JSON shape, one table format."""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np

from vlm_vpr_ros.geodesy import (MAX_DISTANCE_KM, THRESHOLDS_KM, accuracy_table, haversine_km,
                                 median_km)


def errors_km(est: Sequence[tuple[float, float] | None],
              gt: Sequence[tuple[float, float]]) -> list[float | None]:
    """Per-row haversine error; ``None`` where there is no estimate (counts as a miss)."""
    out: list[float | None] = []
    for e, g in zip(est, gt, strict=True):
        if e is None or not all(math.isfinite(v) for v in e):
            out.append(None)
        else:
            out.append(float(haversine_km(e[0], e[1], g[0], g[1])))
    return out


def summarize(errs: Iterable[float | None],
              thresholds: Sequence[float] = THRESHOLDS_KM) -> dict:
    """``{"n", "accuracy": {"1km", ...}, "median_km"}`` — the JSON of ``vlm-vpr evaluate``
    (accuracy keys ``f"{t:g}km"`` for each of ``thresholds``, in km)."""
    errs = list(errs)
    med = median_km(errs)
    return {
        "n": len(errs),
        "accuracy": {k: round(v, 2) for k, v in accuracy_table(errs, thresholds).items()},
        "median_km": None if med is None else round(med, 3),
    }


def summarize_array(errs: np.ndarray, thresholds: Sequence[float] = THRESHOLDS_KM) -> dict:
    """:func:`summarize` of errors as one float array (NaN: no estimate), without a Python
    object per row (millions of rows: ``evaluate``); the same numbers."""
    errs = np.asarray(errs, dtype=np.float64)
    n = len(errs)
    finite = np.where(np.isfinite(errs), errs, np.inf)
    acc = {f"{t:g}km": round(100.0 * int(np.sum(finite <= t)) / n if n else 0.0, 2)
           for t in thresholds}
    med = (float(np.median(np.where(np.isfinite(errs), errs, MAX_DISTANCE_KM))) if n
           else None)
    return {"n": n, "accuracy": acc, "median_km": None if med is None else round(med, 3)}


def threshold_label(key: str) -> str:
    """An accuracy key as a column label: ``"25km"`` stays, ``"0.025km"`` → ``"25m"``."""
    km = float(key.removesuffix("km"))
    return f"{km * 1000:g}m" if km < 1 else key


#: columns added to an accuracy table when its summaries carry ``fixes`` (verified runs)
FIX_COLUMNS = ("fixes", "fix prec 25m", "fix prec 50m")


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}%"


def table_cells(rows: dict[str, dict]) -> tuple[list[str], list[list[str]]]:
    """Header and rows (strings) of an accuracy table: one row per named summary (as returned
    by :func:`summarize`); the columns are the first row's accuracy keys. When any summary has
    a ``fixes`` entry (:func:`fix_metrics`; None: not verified, shown as ``-``), three columns
    follow: the share of answers published as a fix and their precision within 25 m and 50 m.
    The printed tables (:func:`format_table`) and the generated docs tables (the demo's JSON)
    both come from here."""
    first = next(iter(rows.values()), None)
    keys = list(first["accuracy"]) if first else [f"{t:g}km" for t in THRESHOLDS_KM]
    with_fixes = any("fixes" in s for s in rows.values())
    head = ["", "n", *(threshold_label(k) for k in keys), "median km",
            *(FIX_COLUMNS if with_fixes else ())]
    body = []
    for name, s in rows.items():
        med = s.get("median_km")
        cells = [name, str(s["n"]), *(f"{s['accuracy'][k]:.2f}%" for k in keys),
                 "-" if med is None else f"{med:.1f}"]
        if with_fixes:
            fx = s.get("fixes")
            cells += (["-"] * 3 if fx is None else
                      [_pct(fx["rate_pct"]), _pct(fx["precision25_pct"]),
                       _pct(fx["precision50_pct"])])
        body.append(cells)
    return head, body


def format_table(rows: dict[str, dict], title: str = "") -> str:
    """Plain-text table of :func:`table_cells`."""
    return format_cells(*table_cells(rows), title=title)


def format_cells(head: list[str], body: list[list[str]], title: str = "") -> str:
    """Plain-text table of cells (first column left-aligned, the others right-aligned)."""
    first = max([36, *(len(r[0]) + 2 for r in body)])
    widths = [first, 6] + [12 if h == "median km" else max(9, len(h) + 2) for h in head[2:]]

    def line(cells: list[str]) -> str:
        return f"{cells[0]:<{widths[0]}}" + "".join(f"{c:>{w}}"
                                                    for c, w in zip(cells[1:], widths[1:]))

    top = line(head)
    return "\n".join(([title] if title else []) + [top, "-" * len(top)]
                     + [line(r) for r in body])


def read_ground_truth(path) -> dict[str, tuple[float, float]]:
    """Ground truth CSV as {file: (lat, lon)}; columns ``file, lat, lon`` or IM2GPS-style
    ``IMG_ID, LAT, LON``."""
    from vlm_vpr_ros.files.csvio import parse_latlon, read_rows, unique_rows
    from vlm_vpr_ros.errors import DataError

    cols, rows = read_rows(path, "ground truth CSV")
    for fcol, lacol, locol in (("file", "lat", "lon"), ("IMG_ID", "LAT", "LON")):
        if {fcol, lacol, locol} <= set(cols):
            break
    else:
        raise DataError(f"{path}: needs columns file,lat,lon or IMG_ID,LAT,LON; has {cols}")
    return unique_rows(((n, row[fcol], parse_latlon(row[lacol], row[locol], f"{path}:{n}"))
                        for n, row in rows), path, "file")


def _float(v) -> float | None:
    """A finite number of a results CSV, or None (empty, not a plain number: strict, see
    :func:`vlm_vpr_ros.files.csvio.strict_float`)."""
    from vlm_vpr_ros.files.csvio import strict_float

    x = strict_float(v)
    return x if x is not None and math.isfinite(x) else None


RECALL_AT = (1, 5, 10, 20)


def _top_positions(text: str | None) -> list[tuple[float, float]]:
    out = []
    for item in (text or "").split("|"):
        parts = item.split()
        if len(parts) == 2:
            la, lo = _float(parts[0]), _float(parts[1])
            if la is not None and lo is not None:
                out.append((la, lo))
    return out


def fix_metrics(statuses: Sequence[str], errs: Sequence[float | None]) -> dict:
    """``{"n", "rate_pct", "precision25_pct", "precision50_pct"}``: how many answers have
    status ``fix`` (the NavSatFix STATUS_FIX rule, docs/verification.md), their share of all
    rows, and the share of them within 25 m and 50 m of the truth (None without fixes)."""
    fix_err = [e for s, e in zip(statuses, errs, strict=True) if s == "fix"]
    n, nf = len(statuses), len(fix_err)

    def precision(m: float) -> float | None:
        return (round(100.0 * sum(e is not None and e * 1e3 <= m for e in fix_err) / nf, 2)
                if nf else None)
    return {"n": nf, "rate_pct": round(100.0 * nf / n, 2) if n else 0.0,
            "precision25_pct": precision(25.0), "precision50_pct": precision(50.0)}
