"""Core sub-commands: build-map, localize, evaluate, descriptors, demo."""

from __future__ import annotations

import argparse
import json
import logging
import sys

from vlm_vpr_ros.cli.common import (add_descriptor_option_args, add_localizer_args,
                                    add_prior_args, descriptor_options, localizer_config,
                                    make_prior_provider, write_csv_atomic)

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("build-map", help="build a map folder from geotagged reference images",
                       description="Describe every reference image, split the references into "
                                   "submaps and write FAISS indices. Resumable: re-running "
                                   "after an interruption continues where it stopped.")
    p.add_argument("--images", required=True, metavar="DIR", help="folder of reference images")
    p.add_argument("--coords", required=True, metavar="CSV",
                   help="CSV with columns file (relative to DIR), lat, lon")
    p.add_argument("--out", required=True, metavar="MAP", help="map folder to write")
    p.add_argument("--descriptor", default="vlad_rootsift", metavar="NAME",
                   help="descriptor preset (see 'vlm-vpr descriptors'; default vlad_rootsift)")
    p.add_argument("--partition", choices=["country", "kmeans", "none"], default="kmeans",
                   help="submaps: one per country or K-means clusters of positions")
    p.add_argument("--clusters", type=int, default=100, metavar="K",
                   help="K for --partition kmeans (clamped to the data; default 100)")
    p.add_argument("--index", choices=["flat", "fp16"], default="flat",
                   help="flat: exact float32; fp16: half the memory and query time "
                        "(descriptors rounded to float16)")
    p.add_argument("--overwrite", action="store_true", help="replace a different existing map")
    add_descriptor_option_args(p)
    p.set_defaults(func=cmd_build_map)

    p = sub.add_parser("localize", help="localize query images against a map",
                       description="For each query: ask the prior, pick the submap, retrieve "
                                   "the top-p references, re-rank by distance to the prior.")
    p.add_argument("--map", required=True, metavar="MAP")
    p.add_argument("--images", required=True, metavar="DIR", help="folder of query images")
    p.add_argument("--queries", required=True, metavar="CSV", help="CSV with a 'file' column")
    p.add_argument("--out", required=True, metavar="RESULTS.csv")
    p.add_argument("--descriptor", default=None, metavar="NAME",
                   help="expected descriptor (error if the map was built with another)")
    add_descriptor_option_args(p)
    add_prior_args(p)
    add_localizer_args(p)
    p.set_defaults(func=cmd_localize)

    p = sub.add_parser("evaluate", help="accuracy of a results CSV against ground truth")
    p.add_argument("--results", required=True, metavar="RESULTS.csv")
    p.add_argument("--ground-truth", required=True, metavar="CSV",
                   help="file, lat, lon (or IMG_ID, LAT, LON)")
    p.add_argument("--json", action="store_true", help="print only a JSON object on stdout")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("descriptors", help="list the descriptor presets")
    p.set_defaults(func=cmd_descriptors)

    p = sub.add_parser("demo", help="the main job on the shipped demo data (start here)",
                       description="Builds a map from the 71 shipped OpenStreetView-5M images, "
                                   "localizes re-cropped and re-lit copies of them with and "
                                   "without recorded priors, and prints the accuracy table.")
    p.add_argument("--out", default="demo_out", metavar="DIR", help="output folder")
    p.add_argument("--skip-bag", action="store_true", help="skip the bag part of the demo")
    p.set_defaults(func=cmd_demo)


def cmd_build_map(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.map_build import build_map

    m = build_map(args.images, args.coords, args.out, descriptor=args.descriptor,
                  descriptor_config=descriptor_options(args), partition=args.partition,
                  clusters=args.clusters, overwrite=args.overwrite, index=args.index)
    print(f"map {args.out}: {m.n_references} references, {len(m.submaps)} submaps "
          f"({m.partition_method}), descriptor {m.descriptor_identity['name']} "
          f"{m.dim}-D")
    return 0


def cmd_localize(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.batch import RESULT_FIELDS, localize_files
    from vlm_vpr_ros.map_build import read_file_column
    from vlm_vpr_ros.pipeline import LocalizationPipeline

    files = read_file_column(args.queries)
    pipe = LocalizationPipeline.open(args.map, descriptor=args.descriptor,
                                     localizer=localizer_config(args),
                                     descriptor_config=descriptor_options(args))
    provider = make_prior_provider(args)
    from tqdm import tqdm

    try:
        rows = list(tqdm(localize_files(pipe, provider, args.images, files, args.prior_timeout),
                         total=len(files), desc="localize", unit="img", disable=None))
    finally:
        provider.close()
    write_csv_atomic(args.out, RESULT_FIELDS, rows)
    flagged = sum(1 for r in rows if r.get("flags"))
    print(f"{len(rows)} queries localized -> {args.out} ({flagged} with flags)")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.evaluation import evaluate_results_csv, format_table

    summary, extra = evaluate_results_csv(args.results, args.ground_truth)
    if args.json:
        json.dump(summary, sys.stdout)
        sys.stdout.write("\n")
        return 0
    print(format_table({"results": summary}, title=f"accuracy of {args.results}"))
    print(f"uncertainty radius covers the error in {extra['coverage_pct']:.1f}% of rows; "
          f"{extra['flagged']} flagged rows; {extra['missing_gt']} rows without ground truth")
    return 0


def cmd_descriptors(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.descriptors import available_descriptors

    for name, preset in available_descriptors().items():
        dim = preset.dim if preset.dim else "fitted"
        print(f"{name:<22}{dim!s:>8}  {preset.summary}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.demo import run_demo

    return run_demo(args.out, with_bag=not args.skip_bag)
