"""Fix integrity the way GNSS receivers are judged (RTCA DO-229 / SBAS): accuracy, availability,
integrity (protection level, Stanford diagram), time to first fix. Pure: no ROS.

One answer is a :class:`Trial` (truth, estimate, status, protection level ``protection_m``,
optional time and scene). With the alert limit AL (default 50 m), error e and protection level
PL of an answer (docs/evaluation.md, "Integrity"):

* **available** — status ``fix`` and PL < AL (the system says "use me");
* **nominal** — available and e <= PL;
* **misleading information (MI)** — available and PL < e <= AL;
* **hazardously misleading information (HMI, DO-229)** — available and e > AL;
* **unavailable** — status not ``fix``, or PL >= AL;
* **error > PL while FIX** (issue 27's "HMI") — status ``fix`` and e > PL, whatever AL is;
* a fix without a usable PL (no column, empty, NaN, negative, junk) cannot be placed on the
  diagram: it is counted as ``fix_without_pl`` and its error still counts in accuracy and in
  "fixes > AL off".

Repeated frames are one trial, not many: every count is also given per distinct *scene* (a scene
has an HMI when any of its fixes has one). The scene is the query key (results ``file``, bag
``key``) when it names an image, else the truth snapped to a 25 m cell (the report says which).
"""

from __future__ import annotations

import csv
import logging
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np

from vlm_vpr_ros.errors import ConfigError, DataError
from vlm_vpr_ros.evaluation.integrity_plot import plot_stanford
from vlm_vpr_ros.evaluation.metrics import read_ground_truth
from vlm_vpr_ros.files.atomic import atomic_write_json
from vlm_vpr_ros.files.csvio import strict_float
from vlm_vpr_ros.files.outputs import StagedOutput
from vlm_vpr_ros.geodesy import haversine_km

log = logging.getLogger(__name__)

DEFAULT_ALERT_LIMIT_M = 50.0
SCENE_CELL_M = 25.0
_M_PER_DEG = 111_320.0
#: a bag frame key that is only a stamp (``sec.nanosec``) names no scene
_STAMP_KEY = re.compile(r"\d+\.\d{9}")
REGIONS = ("nominal", "misleading", "hazardously_misleading", "unavailable")
JSON_NAME, PNG_NAME = "integrity.json", "stanford.png"

LatLon = tuple[float, float]


@dataclass(frozen=True)
class Trial:
    """One answer: ``truth``/``est`` None when unknown; ``protection_m`` None when not usable;
    ``t_s`` seconds on any clock (time series only); ``key`` the query key ("" = none)."""

    truth: LatLon | None
    est: LatLon | None
    status: str
    protection_m: float | None = None
    t_s: float | None = None
    key: str = ""

    @property
    def fix(self) -> bool:
        return self.status == "fix"

    @property
    def error_m(self) -> float | None:
        if self.truth is None or self.est is None:
            return None
        return 1000.0 * float(haversine_km(self.est[0], self.est[1], *self.truth))


def check_alert_limit(value: object) -> float:
    """A positive finite alert limit (m), else ConfigError (exit 2)."""
    x = strict_float(value) if isinstance(value, str) else (
        float(value) if isinstance(value, (int, float)) and not isinstance(value, bool)
        else None)
    if x is None or not math.isfinite(x) or x <= 0:
        raise ConfigError(f"alert limit must be a positive number of metres, got {value!r}")
    return x


def protection_value(value: object) -> float | None:
    """A usable protection level (finite, >= 0 m) or None (empty, NaN, negative, junk)."""
    x = strict_float(value)
    return x if x is not None and math.isfinite(x) and x >= 0 else None


def region(t: Trial, alert_limit_m: float) -> str | None:
    """The Stanford-diagram region of an answer with truth and estimate ("no_pl" for a fix
    without a usable PL; None when the error is unknown)."""
    e = t.error_m
    if e is None:
        return None
    if not t.fix:
        return "unavailable"
    if t.protection_m is None:
        return "no_pl"
    if t.protection_m >= alert_limit_m:
        return "unavailable"
    if e > alert_limit_m:
        return "hazardously_misleading"
    return "misleading" if e > t.protection_m else "nominal"


def scene_of(t: Trial) -> tuple[str, str]:
    """(source, scene id): ``("key", key)`` or ``("cell25m", "i,j")`` of the truth."""
    key = os.path.basename(t.key.strip()) if t.key else ""
    if key and not _STAMP_KEY.fullmatch(key):
        return "key", key
    if t.truth is None:
        return "none", ""
    lat, lon = t.truth
    i = math.floor(lat * _M_PER_DEG / SCENE_CELL_M)
    band = math.cos(math.radians((i + 0.5) * SCENE_CELL_M / _M_PER_DEG))
    j = math.floor(lon * _M_PER_DEG * max(band, 1e-6) / SCENE_CELL_M)
    return "cell25m", f"{i},{j}"


def nearest_rank(values: Sequence[float], pct: float) -> float | None:
    """The smallest value with at least ``pct`` % of ``values`` at or below it."""
    if not values:
        return None
    s = sorted(values)
    return s[max(0, math.ceil(pct / 100.0 * len(s)) - 1)]


def time_series(trials: Sequence[Trial], t_start: float | None = None,
                t_end: float | None = None) -> dict | None:
    """Time to first fix and the longest gaps; None when no trial has a time. ``longest_gap_s``:
    between consecutive fixes (None with fewer than 2); ``longest_outage_s``: also counting
    start → first fix and last fix → end (the whole span without any fix)."""
    cols = columns_of(trials)
    return _time_series(cols.t_s, cols.fix, t_start, t_end)


def _time_series(t_s: np.ndarray, fix: np.ndarray, t_start: float | None,
                 t_end: float | None) -> dict | None:
    """:func:`time_series` of the columns (NaN: no time)."""
    has = np.isfinite(t_s)
    if not has.any():
        return None
    start = float(t_s[has].min()) if t_start is None else t_start
    end = float(t_s[has].max()) if t_end is None else t_end
    fixes = sorted(float(x) for x in t_s[has & fix])
    gaps = [b - a for a, b in zip(fixes, fixes[1:])]
    edges = [start, *fixes, end]
    return {"span_s": round(end - start, 3),
            "ttff_s": round(fixes[0] - start, 3) if fixes else None,
            "longest_gap_s": round(max(gaps), 3) if gaps else None,
            "longest_outage_s": round(max(b - a for a, b in zip(edges, edges[1:])), 3)}


def _rate(n: int, d: int) -> float | None:
    return round(n / d, 6) if d else None


@dataclass
class Columns:
    """Trials as arrays (a results CSV of millions of rows): ``err_m`` NaN when the error is
    unknown, ``pl`` NaN without a usable protection level, ``t_s`` NaN without a time,
    ``scene`` an id per distinct scene of ``sources`` (:func:`scene_of`)."""

    err_m: np.ndarray
    fix: np.ndarray
    pl: np.ndarray
    scene: np.ndarray
    t_s: np.ndarray
    sources: frozenset[str]


def columns_of(trials: Sequence[Trial]) -> Columns:
    """The columns of ``trials`` (scene ids numbered in order of appearance)."""
    ids: dict[tuple[str, str], int] = {}
    nan = math.nan
    n = len(trials)
    err, pl, t_s = np.full(n, nan), np.full(n, nan), np.full(n, nan)
    fix, scene = np.zeros(n, bool), np.zeros(n, np.int64)
    for k, t in enumerate(trials):
        e = t.error_m
        err[k] = nan if e is None else e
        pl[k] = nan if t.protection_m is None else t.protection_m
        t_s[k] = nan if t.t_s is None else t.t_s
        fix[k] = t.fix
        scene[k] = ids.setdefault(scene_of(t), len(ids))
    return Columns(err, fix, pl, scene, t_s, frozenset(src for src, _ in ids))


def integrity_report(trials: Sequence[Trial] | Columns,
                     alert_limit_m: float = DEFAULT_ALERT_LIMIT_M,
                     t_start: float | None = None, t_end: float | None = None,
                     pl_column: bool | None = None, pl_invalid: int = 0) -> dict:
    """The integrity numbers of ``trials`` (JSON-ready). The protection level is available when
    any trial has a usable one; ``pl_column``: whether the input had a protection_m column
    (reported; None: unknown); ``pl_invalid``: junk PL values seen."""
    al = check_alert_limit(alert_limit_m)
    c = trials if isinstance(trials, Columns) else columns_of(list(trials))
    with np.errstate(invalid="ignore"):
        scored = np.isfinite(c.err_m)
        fixes = scored & c.fix
        has_pl = np.isfinite(c.pl)
        avail = fixes & (c.pl < al)  # a fix with a usable PL below the alert limit
        hmi = avail & (c.err_m > al)
        mi = avail & ~hmi & (c.err_m > c.pl)
        counts = {"nominal": int(np.sum(avail & ~hmi & ~mi)), "misleading": int(mi.sum()),
                  "hazardously_misleading": int(hmi.sum()),
                  "unavailable": int(np.sum(scored & (~c.fix | (has_pl & (c.pl >= al))))),
                  "no_pl": int(np.sum(fixes & ~has_pl))}
        gt_pl = fixes & has_pl & (c.err_m > c.pl)
        gt_al = fixes & (c.err_m > al)
        pl_ge_al = int(np.sum(fixes & has_pl & (c.pl >= al)))
    errs, pls = np.sort(c.err_m[fixes]), np.sort(c.pl[fixes & has_pl])
    n, n_fix, n_all_fix = len(c.fix), int(fixes.sum()), int(c.fix.sum())
    scenes = _scenes(c, scored, {"hmi": hmi, "error_gt_pl": gt_pl, "error_gt_al": gt_al})
    return {
        "alert_limit_m": al, "answers": n, "scored": int(scored.sum()),
        "fixes": n_all_fix, "fixes_scored": n_fix,
        "availability_pct": round(100.0 * n_all_fix / n, 2) if n else None,
        "accuracy_m": {"p50": _r(_rank(errs, 50)), "p95": _r(_rank(errs, 95)),
                       "max": _r(errs[-1] if len(errs) else None)},
        "protection_level": {"available": bool(has_pl.any()), "column": pl_column,
                             "fixes_with_pl": len(pls), "median_m": _r(_rank(pls, 50)),
                             "invalid_values": pl_invalid},
        "regions": counts,
        # published as FIX although PL >= AL: in "unavailable" (DO-229), named apart
        "fixes_pl_at_or_above_al": pl_ge_al,
        "hmi": {"count": int(hmi.sum()), "per_fix": _rate(int(hmi.sum()), n_fix)},
        "error_gt_pl": {"count": int(gt_pl.sum()), "per_fix": _rate(int(gt_pl.sum()), n_fix)},
        "error_gt_al": {"count": int(gt_al.sum()), "per_fix": _rate(int(gt_al.sum()), n_fix)},
        "scenes": scenes,
        "time": _time_series(c.t_s, c.fix, t_start, t_end),
    }


def _rank(sorted_values: np.ndarray, pct: float) -> float | None:
    """:func:`nearest_rank` of values already sorted."""
    n = len(sorted_values)
    return float(sorted_values[max(0, math.ceil(pct / 100.0 * n) - 1)]) if n else None


def _r(x: float | None) -> float | None:
    return None if x is None else round(float(x), 1)


def _scenes(c: Columns, scored: np.ndarray, bad: dict[str, np.ndarray]) -> dict:
    with_fix = len(np.unique(c.scene[scored & c.fix]))
    out = {"source": "+".join(sorted(c.sources)) or "none",
           "n": len(np.unique(c.scene[scored])), "with_fix": with_fix}
    for name, mask in bad.items():
        k = len(np.unique(c.scene[mask]))
        out[name] = {"count": k, "per_scene_with_fix": _rate(k, with_fix)}
    return out


# -- reading results ---------------------------------------------------------------------------

def _latlon(lat: object, lon: object) -> LatLon | None:
    la, lo = strict_float(lat), strict_float(lon)
    if la is None or lo is None or not (math.isfinite(la) and math.isfinite(lo)):
        return None
    return (la, lo) if -90.0 <= la <= 90.0 and -180.0 <= lo <= 180.0 else None


def iter_rows(path: str | os.PathLike[str], what: str = "results CSV"
              ) -> Iterator[tuple[int, dict[str, str]]]:
    """``(line, row)`` of a CSV, streamed (rows of any length; missing cells read as "").
    DataError naming the file and line when the file or its CSV syntax is unusable."""
    path = Path(path)
    line = 1
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            cols = [c.strip() for c in next(reader, [])]
            for cells in reader:
                line = reader.line_num
                yield line, {c: (cells[i] if i < len(cells) else "") for i, c in enumerate(cols)}
    except FileNotFoundError:
        raise DataError(f"{what} not found: {path}") from None
    except (csv.Error, UnicodeDecodeError, ValueError) as exc:
        raise DataError(f"{path}:{line + 1}: malformed CSV: {exc}") from None
    except OSError as exc:
        raise DataError(f"cannot read {what} {path}: {exc.strerror or exc}") from None


def read_trials(results_csv: str | os.PathLike[str],
                truth: dict[str, LatLon] | None = None) -> tuple[list[Trial], dict]:
    """Trials of a results CSV (``vlm-vpr localize``: truth from ``truth`` by ``file`` or its
    base name) or an ``evaluate-bag`` ``frames.csv`` (truth in ``gt_lat``/``gt_lon``, time in
    ``stamp``). Rows without truth are skipped (counted). Returns (trials, info)."""
    base = {os.path.basename(k): v for k, v in (truth or {}).items()}
    trials, info = [], {"rows": 0, "missing_truth": 0, "pl_invalid": 0, "pl_column": False}
    for _, row in iter_rows(results_csv):
        info["pl_column"] = "protection_m" in row  # every row has every header column
        info["rows"] += 1
        key = row.get("file") or row.get("key") or ""
        if truth is not None:
            g = truth.get(key) or base.get(os.path.basename(key))
        else:
            g = _latlon(row.get("gt_lat"), row.get("gt_lon"))
        if g is None:
            info["missing_truth"] += 1
            continue
        raw_pl = (row.get("protection_m") or "").strip()
        pl = protection_value(raw_pl)
        info["pl_invalid"] += bool(raw_pl) and pl is None
        t = strict_float(row.get("stamp"))
        trials.append(Trial(g, _latlon(row.get("lat"), row.get("lon")),
                            (row.get("status") or "").strip(), pl,
                            t if t is not None and math.isfinite(t) else None, key))
    return trials, info


# -- output --------------------------------------------------------------------------------------

def write_report(out_dir: str | os.PathLike[str], rep: dict, trials: Sequence[Trial] | Columns,
                 title: str = "", overwrite: bool = False, staged: bool = True,
                 final_dir: str | os.PathLike[str] | None = None) -> dict:
    """``integrity.json`` and ``stanford.png`` in ``out_dir``; returns ``{name: path}``.
    ``staged``: build a new folder beside ``out_dir`` and swap it in (an existing folder is
    replaced only with ``overwrite`` and only when it is an earlier evaluation); otherwise
    ``out_dir`` is a folder being built already (evaluate-bag's staging folder) that becomes
    ``final_dir`` (the paths returned and written into the JSON)."""
    final = Path(out_dir if staged or final_dir is None else final_dir)
    cols = trials if isinstance(trials, Columns) else columns_of(list(trials))

    def write(folder: Path) -> dict:
        png = plot_stanford(folder / PNG_NAME, cols.pl, cols.err_m, cols.fix, rep["regions"],
                            rep["alert_limit_m"], title)
        paths = {"integrity_json": str(final / JSON_NAME),
                 "stanford_png": str(final / png.name)}
        atomic_write_json(folder / JSON_NAME, {**rep, "outputs": paths})
        return paths

    if not staged:
        return write(Path(out_dir))
    with StagedOutput(final, "evaluation", overwrite, marker=True) as stage:
        paths = write(stage.path)
        stage.commit()
    return paths


def evaluate_integrity(results_csv: str | os.PathLike[str],
                       truth: str | os.PathLike[str] | dict[str, LatLon],
                       alert_limit_m: float = DEFAULT_ALERT_LIMIT_M,
                       out_dir: str | os.PathLike[str] | None = None,
                       overwrite: bool = False, columns: Columns | None = None,
                       pl_column: bool | None = None, pl_invalid: int = 0) -> dict:
    """``vlm-vpr evaluate``'s integrity report of a results CSV; with ``out_dir`` its JSON and
    Stanford diagram are written there (an existing folder without ``overwrite``: a warning,
    nothing written, ``outputs`` empty). ``truth``: the ground-truth CSV or its rows.
    ``columns`` (with ``pl_column``, ``pl_invalid``): the trials as read already by
    ``vlm-vpr evaluate``'s streamed pass (:mod:`.results_csv`; millions of rows)."""
    if columns is not None:
        trials: Sequence[Trial] | Columns = columns
    else:
        if not isinstance(truth, dict):
            truth = read_ground_truth(truth)
        trials, info = read_trials(results_csv, truth)
        pl_column, pl_invalid = info["pl_column"], info["pl_invalid"]
    rep = integrity_report(trials, alert_limit_m, pl_column=pl_column, pl_invalid=pl_invalid)
    rep["outputs"] = {}
    if out_dir is not None:
        try:
            rep["outputs"] = write_report(out_dir, rep, trials, Path(results_csv).name,
                                          overwrite)
        except OSError as exc:  # OutputError included: the printed report still stands
            log.warning("integrity files not written: %s", exc)
    return rep


def default_out_dir(results_csv: str | os.PathLike[str]) -> Path:
    """``RESULTS_integrity/`` beside the results CSV."""
    p = Path(results_csv)
    return p.with_name(p.stem + "_integrity")


def trials_from_frames(rows: Iterable[dict]) -> list[Trial]:
    """Trials of evaluate-bag's in-memory frame rows (every frame; truth None where unpaired)."""
    out = []
    for r in rows:
        t = strict_float(r.get("stamp_ns"))
        out.append(Trial(_latlon(r.get("gt_lat"), r.get("gt_lon")),
                         _latlon(r.get("lat"), r.get("lon")), str(r.get("status") or ""),
                         protection_value(r.get("protection_m")),
                         None if t is None else t / 1e9, str(r.get("key") or "")))
    return out
