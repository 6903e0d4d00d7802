"""``vlm-vpr evaluate``: accuracy, fixes, junk rows and the integrity report of a results CSV
(registered with the core sub-commands in :mod:`vlm_vpr_ros.cli.core`)."""

from __future__ import annotations

import argparse
import json
import sys


def cmd_evaluate(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.evaluation import integrity, integrity_tables
    from vlm_vpr_ros.evaluation.metrics import format_table
    from vlm_vpr_ros.evaluation.results_csv import JUNK, evaluate_results_csv
    from vlm_vpr_ros.files.geojson import is_results_geojson
    from vlm_vpr_ros.files.outputs import check_file_output, check_not_inside

    alert_m = integrity.check_alert_limit(args.alert_limit_m)
    if args.geojson:  # before any work: never over an input or a file of the user's
        check_file_output(args.geojson, "--geojson", [args.results, args.ground_truth],
                          is_results_geojson, "a GeoJSON")
    integrity_out = args.integrity_out or integrity.default_out_dir(args.results)
    # an earlier report's folder is swapped for the new one: never one holding an input
    check_not_inside(integrity_out, [args.results, args.ground_truth], "--integrity-out")
    summary, extra = evaluate_results_csv(args.results, args.ground_truth)
    if args.geojson:
        from vlm_vpr_ros.evaluation.metrics import read_ground_truth
        from vlm_vpr_ros.files.geojson import write_results_geojson

        n = write_results_geojson(args.results, args.geojson,
                                  read_ground_truth(args.ground_truth))
        print(f"GeoJSON: {args.geojson} ({n} points)", file=sys.stderr)
    integ = integrity.evaluate_integrity(  # docs/evaluation.md "Integrity"
        args.results, args.ground_truth, alert_m,
        integrity_out, args.overwrite,
        **extra["integrity"])
    if args.json:
        print(json.dumps({**summary, "recall_pct": extra["recall_pct"], "fixes": extra["fixes"],
                          "coverage68_pct": round(extra["coverage_pct"], 2),
                          "coverage95_pct": (None if extra["coverage95_pct"] is None
                                             else round(extra["coverage95_pct"], 2)),
                          "integrity": integ, "junk_rows": extra["junk_rows"],
                          "junk": extra["junk"]}))
        return 0
    print(format_table({"results": summary}, title=f"accuracy of {args.results}"))
    c95 = extra["coverage95_pct"]
    print(f"coverage: the 68 % radius (uncertainty_m) holds the truth in "
          f"{extra['coverage_pct']:.1f}% of rows, the 95 % radius (radius95_m) in "
          + ("- (no radius95_m column)" if c95 is None else f"{c95:.1f}%")
          + f"; {extra['flagged']} flagged rows (a fallback flag); {extra['missing_gt']} rows "
          "without ground truth")
    if extra["junk_rows"]:
        print(f"junk rows, counted but not scored: {extra['junk_rows']} ("
              + ", ".join(f"{JUNK[k]}: {v}" for k, v in extra["junk"].items())
              + f"); e.g. {extra['junk_examples'][0]}")
    rec, fx = extra["recall_pct"], extra["fixes"]
    print("recall within 25 m: " + ("- (no top_positions column)" if rec is None else
                                    "  ".join(f"R{k} {v:.1f}%" for k, v in rec.items())))
    if fx is None:
        print("fixes: - (no status column: results of an older version)")
    else:
        prec = ("-" if fx["n"] == 0 else f"{fx['precision25_pct']:.1f}% within 25 m, "
                f"{fx['precision50_pct']:.1f}% within 50 m")
        print(f"fixes (status fix): {fx['n']} of {summary['n']} ({fx['rate_pct']:.1f}%); "
              f"precision {prec}")
    print("\n" + integrity_tables.format_report(integ, "integrity (docs/evaluation.md)"))
    for key, path in integ["outputs"].items():
        print(f"{key:>14}: {path}")
    return 0


def add_integrity_args(p: argparse.ArgumentParser, where: str | None) -> None:
    """``--alert-limit-m`` (and, with ``where``, ``--integrity-out`` / ``--overwrite``)."""
    p.add_argument("--alert-limit-m", default="50", metavar="M",
                   help="alert limit of the integrity report (Stanford diagram), m (default 50)")
    if where is not None:
        p.add_argument("--integrity-out", default=None, metavar="DIR",
                       help=f"folder for integrity.json and stanford.png (default: {where})")
        p.add_argument("--overwrite", action="store_true",
                       help="replace an earlier integrity folder (default: keep it, warn)")
