"""Accuracy summaries shared by ``vlm-vpr evaluate``, ``evaluate-bag``, ``priors score`` and the
demo: one JSON shape, one table format."""

from __future__ import annotations

import math
from typing import Iterable, Sequence

from vlm_vpr_ros.geodesy import THRESHOLDS_KM, accuracy_table, haversine_km, median_km


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


def summarize(errs: Iterable[float | None]) -> dict:
    """``{"n", "accuracy": {"1km", ...}, "median_km"}`` — the JSON of ``vlm-vpr evaluate``."""
    errs = list(errs)
    med = median_km(errs)
    return {
        "n": len(errs),
        "accuracy": {k: round(v, 2) for k, v in accuracy_table(errs).items()},
        "median_km": None if med is None else round(med, 3),
    }


def format_table(rows: dict[str, dict], title: str = "") -> str:
    """Plain-text table: one line per named summary (as returned by :func:`summarize`)."""
    keys = [f"{t:g}km" for t in THRESHOLDS_KM]
    head = f"{'':<36}{'n':>6}" + "".join(f"{k:>9}" for k in keys) + f"{'median km':>12}"
    lines = [title] if title else []
    lines += [head, "-" * len(head)]
    for name, s in rows.items():
        med = s.get("median_km")
        lines.append(f"{name:<36}{s['n']:>6}"
                     + "".join(f"{s['accuracy'][k]:>8.2f}%" for k in keys)
                     + f"{'-' if med is None else f'{med:.1f}':>12}")
    return "\n".join(lines)


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


def coverage_pct(errs: Sequence[float | None], radii_m: Sequence[float | None]) -> float:
    """Percent of rows whose error (km) is within their radius (m); a row without an estimate
    or radius counts as not covered."""
    errs = list(errs)
    hits = sum(1 for e, r in zip(errs, radii_m) if e is not None and r is not None
               and e * 1000.0 <= r)
    return 100.0 * hits / len(errs) if errs else 0.0


def evaluate_results_csv(results_csv, ground_truth_csv) -> tuple[dict, dict]:
    """Summary (JSON shape of ``vlm-vpr evaluate``) of a results CSV, plus extra statistics."""
    import os

    from vlm_vpr_ros.files.csvio import read_table

    gt = read_ground_truth(ground_truth_csv)
    gt_base = {os.path.basename(k): v for k, v in gt.items()}
    rows = read_table(results_csv, ("file", "lat", "lon"), "results CSV")
    est, truth, sigma, sigma95, flagged, missing = [], [], [], [], 0, 0
    for row in rows:
        g = gt.get(row.get("file", "")) or gt_base.get(os.path.basename(row.get("file", "")))
        if g is None:
            missing += 1
            continue
        lat, lon = _float(row.get("lat")), _float(row.get("lon"))
        est.append(None if lat is None or lon is None else (lat, lon))
        truth.append(g)
        sigma.append(_float(row.get("uncertainty_m")))
        sigma95.append(_float(row.get("radius95_m")))
        flagged += bool(row.get("flags"))
    errs = errors_km(est, truth)
    extra = {"coverage_pct": coverage_pct(errs, sigma),
             "coverage95_pct": (coverage_pct(errs, sigma95)
                                if any(s is not None for s in sigma95) else None),
             "flagged": flagged, "missing_gt": missing}
    return summarize(errs), extra
