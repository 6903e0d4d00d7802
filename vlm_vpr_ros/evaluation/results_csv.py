"""``vlm-vpr evaluate`` streamed: a results CSV of millions of rows scored against its ground
truth in a few bytes per row, with junk rows counted and reported instead of scored.

Memory: neither file is held as rows or dicts. Each row leaves a few numbers in typed arrays
(its estimate, radii, status, flags, line, and the 64-bit ``hash`` of its file name); the ground
truth is a sorted array of name hashes beside its coordinates, and rows are matched to it by
one vectorized ``searchsorted`` at the end (a file not found by its name is looked up by its
base name, as before). Two different names with one 64-bit hash (about 1e-7 for two million
rows) would be taken as one file. ``benchmarks/bench_evaluate.py`` measures 2,000,000 rows.

Junk (:data:`JUNK`): a latitude/longitude that is not a plain number or out of range (``91``,
``1e999``, ``nan``), only one of the two given, a ``status`` other than ``fix``/``no_fix``
(``FIX``, ``bogus``), a ``p_correct`` outside 0..1, a radius that is not a number >= 0, and a
file scored already (the first row counts). Junk rows are counted by reason, logged with the
first ``file:line``, and left out of every number. An empty estimate is not junk: it is a
query without an answer (a miss). A file of 0 rows (a header only), results or ground truth,
is a DataError saying so, as for every other empty input. ``--results`` and
``--ground-truth`` naming one file is refused (results scored against themselves).
``flagged`` counts rows with a fallback flag (:data:`vlm_vpr_ros.types.FALLBACK_FLAGS`, the
node's meaning), not ``verified`` alone.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
from array import array
from typing import Any, Callable, Sequence

import numpy as np

from vlm_vpr_ros.errors import DataError
from vlm_vpr_ros.evaluation.integrity import Columns
from vlm_vpr_ros.evaluation.metrics import RECALL_AT, _top_positions, summarize_array
from vlm_vpr_ros.files.csvio import NUMBER, parse_latlon, stream_rows
from vlm_vpr_ros.geodesy import THRESHOLDS_KM, haversine_km
from vlm_vpr_ros.types import FALLBACK_FLAGS

log = logging.getLogger(__name__)

JUNK = {"coords": "lat/lon not numbers or out of range", "status": "status not fix/no_fix",
        "p_correct": "p_correct outside 0..1", "radius": "radius not a number >= 0",
        "repeated": "file repeated (the first row scored)"}
STATUSES = ("", "fix", "no_fix")


def _number_reader() -> Callable[[str], float | None]:
    """Cell -> float for hot loops (the rules of :func:`~vlm_vpr_ros.files.csvio.strict_float`):
    None when not a plain decimal number, NaN when empty."""
    match, nan = NUMBER.fullmatch, math.nan

    def num(v: str) -> float | None:
        v = v.strip()
        if not v:
            return nan
        return float(v) if match(v) else None
    return num


_CHUNK = 1 << 18  # rows per vectorized step (bounded temporaries)


class GroundTruth:
    """A ground-truth CSV as sorted name hashes and coordinates (module docstring)."""

    def __init__(self, path: Any) -> None:
        self.path = path
        num = _number_reader()
        hashes, coords, lines = array("q"), array("d"), array("q")
        base_rows, bases = array("q"), array("q")  # only names with a folder part
        with stream_rows(path, "ground truth CSV") as (cols, rows):
            for names in (("file", "lat", "lon"), ("IMG_ID", "LAT", "LON")):
                if set(names) <= set(cols):
                    break
            else:
                raise DataError(f"{path}: needs columns file,lat,lon or IMG_ID,LAT,LON; has "
                                f"{cols}")
            fi, ai, oi = (cols.index(c) for c in names)
            width = max(fi, ai, oi) + 1
            for line, row in rows:
                if len(row) < width:
                    row += [""] * (width - len(row))
                la, lo = num(row[ai]), num(row[oi])
                if la is None or lo is None or not (-90.0 <= la <= 90.0
                                                    and -180.0 <= lo <= 180.0):
                    parse_latlon(row[ai], row[oi], f"{path}:{line}")  # the error, named
                name = row[fi]
                if "/" in name:
                    base_rows.append(len(lines))
                    bases.append(hash(os.path.basename(name)))
                hashes.append(hash(name))
                coords.extend((la, lo))
                lines.append(line)
        if not lines:
            raise DataError(f"ground truth CSV {path}: 0 rows (a header only): nothing to "
                            "score against")
        self.coords = np.frombuffer(coords, dtype=np.float64).reshape(-1, 2)
        h = np.frombuffer(hashes, dtype=np.int64)
        line_of = np.frombuffer(lines, dtype=np.int64)
        order = np.argsort(h, kind="stable")
        hs = h[order]
        keep = np.ones(len(hs), dtype=bool)
        for d in np.flatnonzero(hs[1:] == hs[:-1]):  # one name on two rows
            a, b = order[d], order[d + 1]
            if not np.array_equal(self.coords[a], self.coords[b]):
                raise DataError(f"{path}: lines {line_of[a]} and {line_of[b]} give different "
                                f"values for file {self._name(fi, int(line_of[a]))!r}; keep "
                                "one")
            keep[d + 1] = False
        if not keep.all():
            log.warning("%s: %d repeated file row(s) kept once", path, int((~keep).sum()))
            hs, order = hs[keep], order[keep]
        self._keys, self._rows = hs, order
        del h, line_of, keep
        b = np.frombuffer(bases, dtype=np.int64)
        border = np.argsort(b, kind="stable")  # the first row of each base name
        bs = b[border]
        first = np.ones(len(bs), dtype=bool)
        first[1:] = bs[1:] != bs[:-1]
        self._bkeys = bs[first]
        self._brows = np.frombuffer(base_rows, dtype=np.int64)[border[first]]

    def _name(self, col: int, line: int) -> str:
        with stream_rows(self.path) as (_, rows):
            return next((r[col] for n, r in rows if n == line), "?")

    @staticmethod
    def _find(keys: np.ndarray, rows: np.ndarray, q: np.ndarray) -> np.ndarray:
        if not len(keys):
            return np.full(len(q), -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(keys, q), len(keys) - 1)
        return np.where(keys[pos] == q, rows[pos], -1)

    def lookup(self, names: np.ndarray, base_rows: np.ndarray, bases: np.ndarray
               ) -> np.ndarray:
        """Ground-truth row of each results row: by its name, else (``base_rows``: the rows
        whose name has a folder part, ``bases``: their base names' hashes) by its base name;
        -1: none."""
        g = np.empty(len(names), dtype=np.int64)
        for a in range(0, len(names), _CHUNK):  # bounded temporaries
            g[a:a + _CHUNK] = self._find(self._keys, self._rows, names[a:a + _CHUNK])
        miss = g[base_rows] < 0
        rows, q = base_rows[miss], bases[miss]
        found = self._find(self._keys, self._rows, q)
        found = np.where(found >= 0, found, self._find(self._bkeys, self._brows, q))
        g[rows] = found
        return g


def evaluate_results_csv(results_csv: Any, ground_truth_csv: Any,
                    thresholds: Sequence[float] = THRESHOLDS_KM) -> tuple[dict, dict]:
    """``(summary, extra)`` of a results CSV against ground truth (the JSON shape of
    ``vlm-vpr evaluate``); ``extra`` adds ``junk_rows``, ``junk`` (count by reason) and
    ``junk_examples``."""
    with contextlib.suppress(OSError):
        if os.path.samefile(results_csv, ground_truth_csv):
            raise DataError(f"--results and --ground-truth are the same file ({results_csv}): "
                            "results scored against themselves would be 100 % right")
    truth = GroundTruth(ground_truth_csv)
    num, nan, inf = _number_reader(), math.nan, math.inf
    names, lines = array("q"), array("q")
    base_rows, bases = array("q"), array("q")  # rows whose file name has a folder part
    est, radii, flags = array("d"), array("d"), array("b")
    pls, scenes, pl_invalid = array("d"), array("q"), 0  # the integrity report's columns
    junk: dict[str, int] = dict.fromkeys(JUNK, 0)
    examples: list[tuple[int, str]] = []
    has_status = has95 = False
    with stream_rows(results_csv, "results CSV", ("file", "lat", "lon")) as (cols, rows):
        col = {c: k for k, c in enumerate(cols)}
        width = len(cols)
        c_file, c_lat, c_lon = col["file"], col["lat"], col["lon"]
        c_st, c_p, c_fl = col.get("status"), col.get("p_correct"), col.get("flags")
        c_68, c_95, c_top = col.get("uncertainty_m"), col.get("radius95_m"), \
            col.get("top_positions")
        c_pl = col.get("protection_m")
        for line, row in rows:
            if len(row) < width:
                row += [""] * (width - len(row))
            why = ""
            la, lo = num(row[c_lat]), num(row[c_lon])
            if la is None or lo is None or (la != la) != (lo != lo):
                why = "coords"  # not a number, or only one of the two given
            elif la == la and not (-90.0 <= la <= 90.0 and -180.0 <= lo <= 180.0):
                why = "coords"
            st = row[c_st].strip() if c_st is not None else ""
            if not why and st not in STATUSES:
                why = "status"
            if not why and c_p is not None:
                p = num(row[c_p])
                if p is None or p < 0.0 or p > 1.0:  # NaN (empty) passes
                    why = "p_correct"
            r68 = num(row[c_68]) if c_68 is not None else nan
            r95 = num(row[c_95]) if c_95 is not None else nan
            if not why and (r68 is None or r95 is None or r68 < 0.0 or r95 < 0.0
                            or r68 == inf or r95 == inf):
                why = "radius"
            if why:
                junk[why] += 1
                if len(examples) < 5:
                    examples.append((line, why))
                continue
            name = row[c_file]
            if "/" in name:
                base_rows.append(len(lines))
                bases.append(hash(os.path.basename(name)))
            names.append(hash(name))
            scenes.append(hash(os.path.basename(name)))
            pl = num(row[c_pl]) if c_pl is not None else nan
            if pl is None or pl < 0.0 or pl == inf:  # junk protection level: none, counted
                pl_invalid += 1
                pl = nan
            pls.append(pl)
            lines.append(line)
            est.extend((la, lo))
            radii.extend((r68, r95))
            has95 = has95 or r95 == r95
            has_status = has_status or bool(st)
            flagged = c_fl is not None and not FALLBACK_FLAGS.isdisjoint(row[c_fl].split("|"))
            flags.append((st == "fix") | (flagged << 1))
    if not lines and not sum(junk.values()):  # said as such, not as columns it seems to lack
        raise DataError(f"results CSV {results_csv}: 0 rows (a header only): nothing to "
                        "evaluate")
    g = truth.lookup(*(np.frombuffer(a, dtype=np.int64) for a in (names, base_rows, bases)))
    del names, bases, base_rows
    line_of = np.frombuffer(lines, dtype=np.int64)
    keep = np.zeros(len(g), dtype=bool)  # the first row of each file with ground truth
    seen = np.zeros(len(truth.coords), dtype=bool)
    for a in range(0, len(g), _CHUNK):  # bounded temporaries
        gc = g[a:a + _CHUNK]
        idx = np.flatnonzero(gc >= 0)
        _, first = np.unique(gc[idx], return_index=True)
        cand = idx[first]
        new = cand[~seen[gc[cand]]]
        keep[a + new] = True
        seen[gc[cand]] = True
    del seen
    sel = np.flatnonzero(keep)  # rows scored: ground truth known, file not scored before
    matched = int(np.count_nonzero(g >= 0))
    missing = len(g) - matched
    junk["repeated"] = matched - len(sel)
    if junk["repeated"]:
        again = np.flatnonzero((g >= 0) & ~keep)[:5]
        examples += [(int(line_of[k]), "repeated") for k in again]
    examples = sorted(examples)[:5]
    del keep
    est_a = np.frombuffer(est, dtype=np.float64).reshape(-1, 2)
    rad_a = np.frombuffer(radii, dtype=np.float64).reshape(-1, 2)
    fl = np.frombuffer(flags, dtype=np.int8)[sel]
    gsel = g[sel]
    del g
    n = len(sel)
    errs = np.empty(n, dtype=np.float64)
    covered = [0, 0]
    with np.errstate(invalid="ignore"):
        for a in range(0, n, _CHUNK):  # bounded temporaries
            rows, gt = sel[a:a + _CHUNK], truth.coords[gsel[a:a + _CHUNK]]
            e = est_a[rows]
            errs[a:a + _CHUNK] = haversine_km(e[:, 0], e[:, 1], gt[:, 0], gt[:, 1])
            for k in (0, 1):
                covered[k] += int(np.sum(errs[a:a + _CHUNK] * 1000.0 <= rad_a[rows, k]))
    cov = [100.0 * c / n if n else 0.0 for c in covered]
    fixes = None
    if has_status:
        fix = (fl & 1).astype(bool)
        nf = int(fix.sum())

        def precision(m: float) -> float | None:
            return (round(100.0 * float(np.sum(errs[fix] * 1e3 <= m)) / nf, 2) if nf
                    else None)
        fixes = {"n": nf, "rate_pct": round(100.0 * nf / n, 2) if n else 0.0,
                 "precision25_pct": precision(25.0), "precision50_pct": precision(50.0)}
    recall = (_recall(results_csv, c_top, line_of[sel], truth.coords[gsel])
              if c_top is not None and n else None)
    bad = {k: v for k, v in junk.items() if v}
    shown = [f"{results_csv}:{ln} ({JUNK[w]})" for ln, w in examples]
    if bad:
        log.warning("%s: %d junk row(s) counted, not scored: %s; e.g. %s", results_csv,
                    sum(bad.values()), ", ".join(f"{JUNK[k]} {v}" for k, v in bad.items()),
                    shown[0])
    fix_sel = (fl & 1).astype(bool)
    columns = Columns(errs * 1000.0, fix_sel, np.frombuffer(pls, dtype=np.float64)[sel],
                      np.frombuffer(scenes, dtype=np.int64)[sel], np.full(n, nan),
                      frozenset({"key"}))
    extra = {"integrity": {"columns": columns, "pl_column": c_pl is not None,
                           "pl_invalid": pl_invalid},
             "coverage_pct": cov[0], "coverage95_pct": cov[1] if has95 else None,
             "flagged": int(((fl >> 1) & 1).sum()), "missing_gt": missing,
             "errors_km": ErrorList(errs), "junk_rows": sum(bad.values()), "junk": bad,
             "junk_examples": shown, "recall_pct": recall, "fixes": fixes}
    return summarize_array(errs, thresholds), extra


def _recall(results_csv: Any, c_top: int, lines: np.ndarray, gt: np.ndarray
            ) -> dict[str, float] | None:
    """Recall@k within 25 m over ``top_positions``: a second pass over the scored rows (their
    line numbers, in file order); None when no scored row lists candidates."""
    order = np.argsort(lines, kind="stable")
    want = lines[order]
    hits, any_top, k = dict.fromkeys(RECALL_AT, 0), False, 0
    with stream_rows(results_csv, "results CSV") as (_, rows):
        for line, row in rows:
            if k >= len(want):
                break
            if line != want[k]:
                continue
            i = order[k]
            k += 1
            text = row[c_top] if c_top < len(row) else ""
            if not text:
                continue
            any_top = True
            d = [float(haversine_km(gt[i, 0], gt[i, 1], a, b)) * 1000.0
                 for a, b in _top_positions(text)]
            for j in RECALL_AT:
                hits[j] += any(x <= 25.0 for x in d[:j])
    n = len(lines)
    return {f"@{j}": round(100.0 * v / n, 2) for j, v in hits.items()} if any_top else None


class ErrorList(Sequence):
    """Per-row errors (km) as a read-only sequence over one float array: ``None`` where a row
    has no estimate (what callers of ``errors_km`` expect), no Python object per row."""

    def __init__(self, errs: np.ndarray) -> None:
        self.array = errs

    def __len__(self) -> int:
        return len(self.array)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [None if x != x else x for x in self.array[i].tolist()]
        x = float(self.array[i])
        return None if x != x else x
