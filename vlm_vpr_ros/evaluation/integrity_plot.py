"""The Stanford diagram (error vs protection level) of an integrity report, drawn offline with
matplotlib's Agg backend like :mod:`vlm_vpr_ros.evaluation.plots`.

Log-log axes from 1 m (values below sit on the edge); fixes are a 2-D histogram coloured by
counts; answers that are not fixes (``NO_FIX``) are grey crosses; the four regions of
:mod:`.integrity` are shaded and labelled with their counts (over every answer, as in the JSON).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np

from vlm_vpr_ros.evaluation.plots import _pyplot, _save

AXIS_M = (1.0, 10_000.0)
_COLOURS = {"nominal": "#2e7d32", "misleading": "#f9a825", "hazardously_misleading": "#c62828",
            "unavailable": "#757575"}
_LABELS = {"nominal": "nominal", "misleading": "misleading (MI)",
           "hazardously_misleading": "hazardously misleading (HMI)",
           "unavailable": "unavailable"}


def plot_stanford(path: str | os.PathLike[str], pl: np.ndarray, err: np.ndarray,
                  fix: np.ndarray, counts: Mapping[str, int], alert_limit_m: float,
                  title: str = "", dpi: int = 110) -> Path:
    """Write the Stanford diagram to ``path`` (PNG); returns the path. ``pl``, ``err``, ``fix``:
    protection level (m, NaN: none), error (m, NaN: unknown) and fix flag of every answer (those
    with both are drawn); ``counts``: the answers per region
    (:data:`vlm_vpr_ros.evaluation.integrity.REGIONS`) and ``no_pl`` (fixes without a
    protection level), as the report counted them."""
    plt = _pyplot()
    from matplotlib.colors import LogNorm

    lo, hi = AXIS_M
    al = float(alert_limit_m)
    hi = max(hi, 4.0 * al)
    drawn = np.isfinite(pl) & np.isfinite(err)
    xy = np.clip(np.stack([pl[drawn], err[drawn]], axis=1), lo, hi)
    fix_xy, other_xy = xy[fix[drawn]], xy[~fix[drawn]]
    fig, ax = plt.subplots(figsize=(7.2, 6.0))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    # regions: nominal (e <= PL < AL), MI (PL < e <= AL), HMI (PL < AL < e), unavailable (PL >= AL)
    ax.fill_between([lo, al], [lo, al], [lo, lo], color=_COLOURS["nominal"], alpha=0.10, lw=0)
    ax.fill_between([lo, al], [al, al], [lo, al], color=_COLOURS["misleading"], alpha=0.14, lw=0)
    ax.fill_between([lo, al], [hi, hi], [al, al], color=_COLOURS["hazardously_misleading"],
                    alpha=0.12, lw=0)
    ax.fill_between([al, hi], [hi, hi], [lo, lo], color=_COLOURS["unavailable"], alpha=0.12, lw=0)
    ax.plot([lo, hi], [lo, hi], color="#333333", lw=0.9, ls="-", label="error = protection level")
    ax.axvline(al, color="#b71c1c", lw=1.1, ls="--", label=f"alert limit {al:g} m")
    ax.plot([lo, al], [al, al], color="#b71c1c", lw=1.1, ls="--")
    if len(other_xy):
        o = other_xy
        ax.scatter(o[:, 0], o[:, 1], marker="x", s=14, lw=0.7, color="#9e9e9e", zorder=3,
                   label=f"not a fix (NO_FIX): {len(other_xy)}")
    if len(fix_xy):
        f = fix_xy
        from matplotlib.ticker import FuncFormatter

        bins = np.logspace(np.log10(lo), np.log10(hi), 33)
        _, _, _, img = ax.hist2d(f[:, 0], f[:, 1], bins=[bins, bins], cmap="viridis",
                                 norm=LogNorm(vmin=1), cmin=1, zorder=4)
        bar = fig.colorbar(img, ax=ax, label="fixes per bin", shrink=0.8)
        whole = FuncFormatter(lambda v, _: f"{v:g}" if v == round(v) else "")
        bar.ax.yaxis.set_major_formatter(whole)
        bar.ax.yaxis.set_minor_formatter(whole)
    spots = {"nominal": (al / 1.25, lo * 1.25, "right", "bottom"),
             "misleading": (lo * 1.25, al / 1.25, "left", "top"),
             "hazardously_misleading": (lo * 1.25, hi / 1.25, "left", "top"),
             "unavailable": (hi / 1.25, al, "right", "center")}
    for name, (x, y, ha, va) in spots.items():
        ax.text(x, y, f"{_LABELS[name]}: {counts[name]}", ha=ha, va=va, fontsize=9,
                color=_COLOURS[name], weight="bold", zorder=5,
                bbox={"fc": "white", "alpha": 0.75, "ec": "none", "pad": 1.5})
    ax.set_xlabel("protection level [m] (log)")
    ax.set_ylabel("horizontal error [m] (log)")
    note = (f"; {counts['no_pl']} fixes without a protection level (not drawn)"
            if counts["no_pl"] else "")
    ax.set_title((title + "\n" if title else "") + f"Stanford diagram, alert limit {al:g} m"
                 + note, fontsize=9.5)
    ax.grid(True, which="major", lw=0.3, alpha=0.6)
    ax.legend(loc="lower right", fontsize=7.5, framealpha=0.9)
    fig.tight_layout()
    return _save(fig, path, dpi)
