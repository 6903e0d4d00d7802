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
    head = f"{'':<28}{'n':>6}" + "".join(f"{k:>9}" for k in keys) + f"{'median km':>12}"
    lines = [title] if title else []
    lines += [head, "-" * len(head)]
    for name, s in rows.items():
        med = s.get("median_km")
        lines.append(f"{name:<28}{s['n']:>6}"
                     + "".join(f"{s['accuracy'][k]:>8.2f}%" for k in keys)
                     + f"{'-' if med is None else f'{med:.1f}':>12}")
    return "\n".join(lines)
