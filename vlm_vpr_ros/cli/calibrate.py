"""``vlm-vpr calibrate``: calibrate a map's 68 / 95 % radii and its ``p_correct`` on the user's
own labelled queries.

Split-conformal: for the results of ``vlm-vpr localize`` with this map, the factors that make
``error <= k * radius`` hold for 68 % (95 %) of the rows (finite-sample quantile), separately for
rows with and without a prior, multiply the factors the results were produced with. They are
stored as the ``user`` section of the map's ``calibration.json`` (the build-time leave-one-out
section is kept) and override it from the next start of the node or CLI. docs/fusion.md.
Verified fixes are left out of the radius factors (their radii are the place's, not the
posterior's).

``p_correct`` (docs/verification.md): the evidence scores (``inlier_ratio``) of the answers that
were wrong by more than 25 m join the map's leave-one-out wrong answers (``user`` section of
``verification.json``; a map without one gets a user-only calibration).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
from pathlib import Path
from typing import Any

from vlm_vpr_ros.errors import DataError

log = logging.getLogger(__name__)
MIN_ROWS = 10


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate", help="calibrate a map's uncertainty radii on labelled queries",
        description="Conformal calibration of the 68 % / 95 % radii from a results CSV of "
                    "'vlm-vpr localize' on this map and its ground truth; stored in the map's "
                    "calibration.json (docs/fusion.md).")
    p.add_argument("--results", metavar="RESULTS.csv",
                   help="results of 'vlm-vpr localize' on this map (with --ground-truth)")
    p.add_argument("--ground-truth", metavar="CSV", help="file, lat, lon (or IMG_ID, LAT, LON)")
    p.add_argument("--map", required=True, metavar="MAP", help="the map the results came from")
    p.add_argument("--dry-run", action="store_true", help="print the factors, write nothing")
    p.add_argument("--conditions", metavar="LIST", default=None,
                   help="redo the map's leave-one-out verification calibration under these "
                        "query conditions (comma-separated: full, fit<W>x<H>, jpeg<Q>_<W>x<H>; "
                        "'default': full,fit640x480,fit480x360,jpeg40_640x480); needs the "
                        "reference images (the map's own, the folder a build-map --images "
                        "map recorded, or --reference-images); docs/verification.md")
    p.add_argument("--reference-images", metavar="DIR", default="",
                   help="the folder the map was built from (for --conditions; default: the "
                        "one the build recorded, every picture checked against it)")
    p.add_argument("--degraded-queries", type=int, default=None, metavar="N",
                   help="references queried under each degraded condition (default 60: the "
                        "cost bound; more keeps more fixes at the same threshold)")
    p.add_argument("--feature-option", metavar="KEY=VALUE", action="append", default=[],
                   help="with --conditions: local feature setting not stored in the map, "
                        "repeatable (a learned preset's device=cuda, threads=N, weights=PATH)")
    p.add_argument("--matcher-option", metavar="KEY=VALUE", action="append", default=[],
                   help="with --conditions: matcher setting, repeatable (device=cuda, ...)")
    p.set_defaults(func=cmd_calibrate)


def _num(v) -> float | None:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) and x > 0 else None


def results_rows(results_csv, required=("file", "lat", "lon")) -> list[dict[str, str]]:
    """The rows of a results CSV of ``vlm-vpr localize``, checked before they count: a row
    repeated is kept once (warning with the line numbers), a file given twice with other
    values, a latitude/longitude out of range, a non-finite or negative radius or
    ``inlier_ratio`` (the evidence score, >= 0), a ``p_correct`` outside 0..1, ``nan`` anywhere
    and an unknown ``status`` are a
    DataError naming ``file:line`` and the field (one wrong answer must not count 20 times,
    nor a made-up score move ``p_correct``)."""
    from vlm_vpr_ros.evaluation.results_csv import STATUSES
    from vlm_vpr_ros.files.csvio import parse_latlon, parse_number, read_rows, unique_rows

    _, rows = read_rows(results_csv, "results CSV", required)
    checked = []
    for line, row in rows:
        where = f"{results_csv}:{line}"
        if (row.get("lat") or "").strip() or (row.get("lon") or "").strip():
            parse_latlon(row.get("lat"), row.get("lon"), where)
        for field, lo, hi in (("uncertainty_m", 0.0, math.inf), ("radius95_m", 0.0, math.inf),
                              ("inlier_ratio", 0.0, math.inf), ("p_correct", 0.0, 1.0)):
            value = (row.get(field) or "").strip()
            if value and not lo <= parse_number(value, where, field) <= hi:
                raise DataError(f"{where}: {field} {value} is out of range [{lo:g}, {hi:g}]")
        if (row.get("status") or "").strip() not in STATUSES:
            raise DataError(f"{where}: status {row.get('status')!r} is not one of "
                            f"{', '.join(repr(s) for s in STATUSES[1:])} (or empty)")
        checked.append((line, row["file"], tuple(sorted((k, v or "") for k, v in row.items()
                                                        if k is not None))))
    unique = unique_rows(checked, results_csv, "file")
    return [dict(items) for items in unique.values()]


def calibration_ratios(results_csv, ground_truth_csv) -> dict[str, dict[str, list[float]]]:
    """error / radius per regime ("prior" / "no_prior") and level ("68" / "95")."""
    from vlm_vpr_ros.evaluation.metrics import read_ground_truth
    from vlm_vpr_ros.geodesy import haversine_km

    gt = read_ground_truth(ground_truth_csv)
    by_base = {os.path.basename(k): v for k, v in gt.items()}
    rows = results_rows(results_csv, ("file", "lat", "lon", "uncertainty_m", "radius95_m"))
    out: dict[str, dict[str, list[float]]] = {r: {"68": [], "95": []}
                                              for r in ("prior", "no_prior")}
    for row in rows:
        g = gt.get(row["file"]) or by_base.get(os.path.basename(row["file"]))
        r68, r95 = _num(row.get("uncertainty_m")), _num(row.get("radius95_m"))
        try:
            lat, lon = float(row["lat"]), float(row["lon"])
        except (TypeError, ValueError):
            continue
        if g is None or r68 is None or r95 is None or not (math.isfinite(lat)
                                                            and math.isfinite(lon)):
            continue
        err_m = float(haversine_km(g[0], g[1], lat, lon)) * 1000.0
        if row.get("status") == "fix":
            continue  # a verified fix's radii are the place's, not the posterior's
        regime = "prior" if (row.get("prior_lat") or "").strip() else "no_prior"
        out[regime]["68"].append(err_m / r68)
        out[regime]["95"].append(err_m / r95)
    return out


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Writes calibration.json and the manifest of the map: under the map's writer lock (a
    ``map add`` between reading the manifest and writing it back would otherwise be lost)."""
    import contextlib

    from vlm_vpr_ros.maps.transaction import edit_lock

    if args.results is None and args.conditions is None:
        raise DataError("calibrate: give --results and --ground-truth, or --conditions")
    if (args.results is None) != (args.ground_truth is None):
        raise DataError("calibrate: --results and --ground-truth go together")
    with (contextlib.nullcontext() if args.dry_run else edit_lock(Path(args.map), "calibrate")):
        if args.conditions is not None:
            _calibrate_conditions(args)
        return _calibrate(args) if args.results is not None else 0


def _calibrate_conditions(args: argparse.Namespace) -> None:
    """``--conditions``: the leave-one-out calibration of p_correct and the protection level
    again, under the given query conditions (a user section of an earlier calibration is
    kept)."""
    from vlm_vpr_ros.cli.common import parse_kv
    from vlm_vpr_ros.mapping.local_features import calibrate_map
    from vlm_vpr_ros.localization.verification.p_correct import (load_doc, save_doc,
                                                                   validate)
    from vlm_vpr_ros.localization.verification.conditions import parse_conditions
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    spec = None if args.conditions.strip() == "default" else args.conditions
    if args.degraded_queries is not None and args.degraded_queries < 1:
        raise DataError(f"--degraded-queries must be >= 1, got {args.degraded_queries}")
    names = [c.name for c in parse_conditions(spec)]
    if args.reference_images and not Path(args.reference_images).is_dir():
        raise DataError(f"--reference-images {args.reference_images}: not a folder")
    if args.dry_run:
        print(f"dry run: would calibrate under {','.join(names)}")
        return
    ref_map = ReferenceMap.load(args.map)
    _check_pictures(ref_map, names, args.reference_images)
    old = load_doc(ref_map)
    doc = calibrate_map(ref_map, conditions=names, images_dir=args.reference_images or None,
                        degraded_queries=args.degraded_queries,
                        feature_options=parse_kv(args.feature_option),
                        matcher_options=parse_kv(args.matcher_option))
    if doc is None:
        raise DataError(f"{args.map}: the map stores no local features: nothing to calibrate")
    if old is not None and old.get("user"):
        doc["user"] = old["user"]
        save_doc(ref_map, validate(doc, "verification calibration"))
    loo = doc["loo"]
    print(f"verification calibration under {','.join(doc['conditions'])}: {loo['queries']} "
          f"leave-one-out queries ({loo['wrong']} wrong, {loo['right']} right), protection "
          f"residual {doc['protection']['residual_m']:g} m, {loo['seconds']:g} s")
    print(threshold_summary(doc))


def threshold_summary(doc: dict, level: float = 0.99, show: int = 5) -> str:
    """What sets the fix threshold of a verification calibration: the inlier ratio that
    ``p_correct >= level`` needs (asked of the calibrated model itself, the user's negatives
    included) and the strongest wrong leave-one-out answers (a pair of references showing one
    view but geotagged far apart holds every answer below it back: correct or remove one of
    them; docs/verification.md section 7)."""
    from vlm_vpr_ros.localization.verification.evidence import AMBIGUOUS_RATIO
    from vlm_vpr_ros.localization.verification.p_correct import PCorrect

    model = PCorrect.from_doc(doc)
    null = model.null_scores
    # p_correct steps up just above a wrong answer's score; below AMBIGUOUS_RATIO its cap
    # r / (1 + r) reaches the level at level / (1 - level): the threshold is one of these
    steps = sorted({0.0, AMBIGUOUS_RATIO, level / (1.0 - level), *null.tolist()})
    need = next((t for t in steps
                 if model.p_correct(math.nextafter(t, math.inf)) >= level), None)
    if need is None:
        head = (f"no score reaches p_correct >= {level:g} with {len(null)} wrong "
                "leave-one-out answers: no fix on this calibration")
    else:
        head = (f"p_correct >= {level:g} needs an inlier ratio above {need:g} (wrong "
                f"leave-one-out answers: {len(null)}, the strongest {int((null >= need).sum())} "
                f"score >= {need:g})")
    lines = [head]
    for r in doc.get("strongest_wrong", [])[:show]:
        lines.append(f"  wrong {r.get('condition')}: {r.get('query')} -> {r.get('answer')}, "
                     f"{r.get('error_m')} m off, {r.get('inliers')} inliers, ratio "
                     f"{r.get('score')}")
    return "\n".join(lines)


def _check_pictures(ref_map: Any, names: list[str], reference_images: str) -> None:
    """Conditions other than ``full`` need the reference pictures: without them the
    calibration would cover full-size queries only and replace the one the map has (a map
    calibrated under four conditions would silently stop giving fixes). Refused up front;
    the old calibration stays."""
    from vlm_vpr_ros.maps.map_images import pictures_problem

    need = [n for n in names if n != "full"]
    if not need:
        return
    why = pictures_problem(ref_map.path, ref_map.manifest, ref_map.all_ids(),
                           reference_images or "")
    if why:
        raise DataError(f"{ref_map.path}: conditions {','.join(need)} need the reference "
                        f"pictures: {why}; the old calibration was kept")


def _calibrate(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.localization.fusion.calibration import (CALIBRATION_FORMAT,
                                                             CALIBRATION_VERSION, conformal_factor,
                                                             load_calibration, save_calibration)
    from vlm_vpr_ros.localization.localizer import Localizer
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    ref_map = ReferenceMap.load(args.map)
    loc = Localizer(ref_map)
    ratios = calibration_ratios(args.results, args.ground_truth)
    doc = load_calibration(ref_map) or {"format": CALIBRATION_FORMAT,
                                        "version": CALIBRATION_VERSION, "visual_scale": None,
                                        "beta": 1.0, "miss_prob": 0.05, "regimes": {},
                                        "loo": {"queries": 0}}
    user = dict(doc.get("user") or {})
    done = 0
    for regime, r in ratios.items():
        n = len(r["68"])
        if n == 0:
            continue
        cov68 = 100.0 * sum(x <= 1.0 for x in r["68"]) / n
        cov95 = 100.0 * sum(x <= 1.0 for x in r["95"]) / n
        if n < MIN_ROWS:
            print(f"{regime}: {n} rows (< {MIN_ROWS}), not calibrated; coverage now "
                  f"{cov68:.1f}% / {cov95:.1f}%")
            continue
        k68_old, k95_old = loc.calibration_factors(regime == "prior")
        c68, c95 = conformal_factor(r["68"], 0.68), conformal_factor(r["95"], 0.95)
        user[regime] = {"k68": k68_old * c68, "k95": k95_old * c95, "n": n,
                        "results": os.path.basename(str(args.results))}
        done += 1
        print(f"{regime}: {n} rows; coverage now 68 %: {cov68:.1f}%, 95 %: {cov95:.1f}%; "
              f"radii x{c68:.3g} / x{c95:.3g} -> factors k68 {user[regime]['k68']:.4g}, "
              f"k95 {user[regime]['k95']:.4g}")
    verified = verification_negatives(args.results, args.ground_truth)
    if not done and verified is None:
        raise DataError(f"{args.results}: need at least {MIN_ROWS} rows with ground truth, "
                        "estimates and radii (uncertainty_m, radius95_m) in one regime, or "
                        f"{MIN_ROWS} verified rows (inlier_ratio)")
    if args.dry_run:
        print("dry run: nothing written")
        return 0
    if done:
        doc["user"] = user
        path = save_calibration(ref_map, doc)
        print(f"wrote {path} (used from the next start of the node / CLI)")
    if verified is not None:
        from vlm_vpr_ros.localization.verification.p_correct import (load_doc, save_doc,
                                                                     with_user_negatives)

        scores, n = verified
        path = save_doc(ref_map, with_user_negatives(
            load_doc(ref_map), scores, n, os.path.basename(str(args.results))))
        print(f"wrote {path}: p_correct now also rests on {len(scores)} wrong answers of "
              f"yours (used from the next start)")
    return 0


def verification_negatives(results_csv, ground_truth_csv) -> tuple[list[float], int] | None:
    """Scores (``inlier_ratio``) of the verified rows more than 25 m off, and the number of
    verified rows with ground truth; None with fewer than MIN_ROWS of them. Prints the fix
    rate and precision of these rows."""
    from vlm_vpr_ros.evaluation.metrics import read_ground_truth
    from vlm_vpr_ros.geodesy import haversine_km

    gt = read_ground_truth(ground_truth_csv)
    by_base = {os.path.basename(k): v for k, v in gt.items()}
    rows = results_rows(results_csv)
    wrong, n, fixes, fix_ok = [], 0, 0, 0
    for row in rows:
        g = gt.get(row["file"]) or by_base.get(os.path.basename(row["file"]))
        try:
            lat, lon, score = float(row["lat"]), float(row["lon"]), float(
                row.get("inlier_ratio") or "nan")
        except (TypeError, ValueError):
            continue
        if g is None or not all(math.isfinite(v) for v in (lat, lon, score)):
            continue
        n += 1
        err_m = float(haversine_km(g[0], g[1], lat, lon)) * 1000.0
        if err_m > 25.0:
            wrong.append(score)
        if row.get("status") == "fix":
            fixes += 1
            fix_ok += err_m <= 25.0
    if n < MIN_ROWS:
        if n:
            print(f"verification: {n} verified rows (< {MIN_ROWS}), p_correct not refined")
        return None
    print(f"verification: {n} verified rows, {len(wrong)} wrong by > 25 m; fixes {fixes} "
          f"({fix_ok} within 25 m)")
    return wrong, n
