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

from vlm_vpr_ros.errors import ConfigError, DataError
from vlm_vpr_ros.evaluation.integrity_plot import plot_stanford
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
    times = [t.t_s for t in trials if t.t_s is not None and math.isfinite(t.t_s)]
    if not times:
        return None
    start = min(times) if t_start is None else t_start
    end = max(times) if t_end is None else t_end
    fixes = sorted(t.t_s for t in trials if t.fix and t.t_s is not None
                   and math.isfinite(t.t_s))
    gaps = [b - a for a, b in zip(fixes, fixes[1:])]
    edges = [start, *fixes, end]
    return {"span_s": round(end - start, 3),
            "ttff_s": round(fixes[0] - start, 3) if fixes else None,
            "longest_gap_s": round(max(gaps), 3) if gaps else None,
            "longest_outage_s": round(max(b - a for a, b in zip(edges, edges[1:])), 3)}


def _rate(n: int, d: int) -> float | None:
    return round(n / d, 6) if d else None


def integrity_report(trials: Sequence[Trial], alert_limit_m: float = DEFAULT_ALERT_LIMIT_M,
                     t_start: float | None = None, t_end: float | None = None,
                     pl_column: bool | None = None, pl_invalid: int = 0) -> dict:
    """The integrity numbers of ``trials`` (JSON-ready). The protection level is available when
    any trial has a usable one; ``pl_column``: whether the input had a protection_m column
    (reported; None: unknown); ``pl_invalid``: junk PL values seen."""
    al = check_alert_limit(alert_limit_m)
    trials = list(trials)
    scored = [t for t in trials if t.error_m is not None]
    fixes = [t for t in scored if t.fix]
    errs = [t.error_m for t in fixes]
    counts = dict.fromkeys((*REGIONS, "no_pl"), 0)
    for t in scored:
        counts[region(t, al)] += 1
    pls = [t.protection_m for t in fixes if t.protection_m is not None]
    has_pl = any(t.protection_m is not None for t in trials)
    gt_pl = [t for t in fixes if t.protection_m is not None and t.error_m > t.protection_m]
    gt_al = [t for t in fixes if t.error_m > al]
    hmi = [t for t in scored if region(t, al) == "hazardously_misleading"]
    scenes = _scenes(scored, {"hmi": hmi, "error_gt_pl": gt_pl, "error_gt_al": gt_al})
    n_fix = len(fixes)
    return {
        "alert_limit_m": al, "answers": len(trials), "scored": len(scored),
        "fixes": sum(t.fix for t in trials), "fixes_scored": n_fix,
        "availability_pct": (round(100.0 * sum(t.fix for t in trials) / len(trials), 2)
                             if trials else None),
        "accuracy_m": {"p50": _r(nearest_rank(errs, 50)), "p95": _r(nearest_rank(errs, 95)),
                       "max": _r(max(errs) if errs else None)},
        "protection_level": {"available": has_pl, "column": pl_column,
                             "fixes_with_pl": len(pls), "median_m": _r(nearest_rank(pls, 50)),
                             "invalid_values": pl_invalid},
        "regions": counts,
        # published as FIX although PL >= AL: in "unavailable" (DO-229), named apart
        "fixes_pl_at_or_above_al": sum(t.protection_m is not None and t.protection_m >= al
                                       for t in fixes),
        "hmi": {"count": len(hmi), "per_fix": _rate(len(hmi), n_fix)},
        "error_gt_pl": {"count": len(gt_pl), "per_fix": _rate(len(gt_pl), n_fix)},
        "error_gt_al": {"count": len(gt_al), "per_fix": _rate(len(gt_al), n_fix)},
        "scenes": scenes,
        "time": time_series(trials, t_start, t_end),
    }


def _r(x: float | None) -> float | None:
    return None if x is None else round(float(x), 1)


def _scenes(scored: Sequence[Trial], bad: dict[str, list[Trial]]) -> dict:
    of = {id(t): scene_of(t) for t in scored}
    sources = sorted({s for s, _ in of.values()})
    all_ids = set(of.values())  # (source, id): a key never equals a cell by accident
    with_fix = {of[id(t)] for t in scored if t.fix}
    out = {"source": "+".join(sources) or "none", "n": len(all_ids), "with_fix": len(with_fix)}
    for name, items in bad.items():
        ids = {of[id(t)] for t in items}
        out[name] = {"count": len(ids), "per_scene_with_fix": _rate(len(ids), len(with_fix))}
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

def stanford_points(trials: Sequence[Trial], alert_limit_m: float
                    ) -> tuple[list[tuple[float, float, bool]], dict[str, int]]:
    """The Stanford diagram's points (PL, error, is a fix) and its counts per region, ``no_pl``
    for fixes without a protection level (drawn by :func:`plot_stanford`)."""
    counts = dict.fromkeys((*REGIONS, "no_pl"), 0)
    points = []
    for t in trials:
        reg = region(t, alert_limit_m)
        if reg is None:
            continue
        counts[reg] += 1
        if t.protection_m is not None:
            points.append((t.protection_m, t.error_m, t.fix))
    return points, counts


def write_report(out_dir: str | os.PathLike[str], rep: dict, trials: Sequence[Trial],
                 title: str = "", overwrite: bool = False, staged: bool = True,
                 final_dir: str | os.PathLike[str] | None = None) -> dict:
    """``integrity.json`` and ``stanford.png`` in ``out_dir``; returns ``{name: path}``.
    ``staged``: build a new folder beside ``out_dir`` and swap it in (an existing folder is
    replaced only with ``overwrite`` and only when it is an earlier evaluation); otherwise
    ``out_dir`` is a folder being built already (evaluate-bag's staging folder) that becomes
    ``final_dir`` (the paths returned and written into the JSON)."""
    final = Path(out_dir if staged or final_dir is None else final_dir)

    def write(folder: Path) -> dict:
        png = plot_stanford(folder / PNG_NAME, *stanford_points(trials, rep["alert_limit_m"]),
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
                       overwrite: bool = False) -> dict:
    """``vlm-vpr evaluate``'s integrity report of a results CSV; with ``out_dir`` its JSON and
    Stanford diagram are written there (an existing folder without ``overwrite``: a warning,
    nothing written, ``outputs`` empty). ``truth``: the ground-truth CSV or its rows."""
    if not isinstance(truth, dict):
        from vlm_vpr_ros.evaluation.metrics import read_ground_truth

        truth = read_ground_truth(truth)
    trials, info = read_trials(results_csv, truth)
    rep = integrity_report(trials, alert_limit_m, pl_column=info["pl_column"],
                           pl_invalid=info["pl_invalid"])
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
