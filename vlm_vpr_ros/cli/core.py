"""Core sub-commands: build-map, localize (:mod:`.localize`), evaluate (:mod:`.evaluate`),
descriptors, demo."""

from __future__ import annotations

import argparse
import logging

from vlm_vpr_ros.cli.common import (add_descriptor_option_args, add_localizer_args,
                                    add_local_feature_args, add_prior_args,
                                    add_verification_args, descriptor_options,
                                    local_feature_options)
from vlm_vpr_ros.cli.distributed import add_engine_args, cmd_build_map_ray, engine_options
from vlm_vpr_ros.cli.evaluate import add_integrity_args, cmd_evaluate
from vlm_vpr_ros.cli.localize import cmd_localize
from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.files.outputs import check_not_inside

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("build-map", help="build a map folder from geotagged reference images",
                       description="Describe every reference image, split the references into "
                                   "submaps and write FAISS indices. Resumable: re-running "
                                   "after an interruption continues where it stopped. With "
                                   "--bag: a teach run (camera + NavSatFix rosbag2 bag) gives "
                                   "the references (see docs/teach.md). With --descriptors: "
                                   "precomputed descriptors, out of core (docs/planet_scale.md).")
    p.add_argument("--images", metavar="DIR", help="folder of reference images")
    p.add_argument("--descriptors", metavar="SRC",
                   help="precomputed descriptors instead of images: an (n, dim) float32 .npy "
                        "aligned with --coords, or a folder of .npy(+.ids.txt)/.parquet "
                        "shards (docs/planet_scale.md); out-of-core, no model loaded")
    p.add_argument("--coords", metavar="CSV",
                   help="CSV with columns file (relative to DIR), lat, lon")
    add_teach_args(p)
    p.add_argument("--out", required=True, metavar="MAP", help="map folder to write")
    p.add_argument("--descriptor", default="vlad_rootsift", metavar="NAME",
                   help="descriptor preset (see 'vlm-vpr descriptors'; default vlad_rootsift)")
    p.add_argument("--partition", choices=["country", "kmeans", "none"], default="kmeans",
                   help="submaps: one per country or K-means clusters of positions")
    p.add_argument("--clusters", type=int, default=100, metavar="K",
                   help="K for --partition kmeans (clamped to the data; default 100)")
    p.add_argument("--index", choices=["flat", "fp16", "pq", "auto"], default=None,
                   help="flat: exact float32; fp16: half the memory and query time "
                        "(descriptors rounded to float16); pq: PQ fast-scan codes in RAM + "
                        "exact re-rank from fp16 vectors on disk (planet scale); auto: per "
                        "submap within --ram-budget-mb (default: flat, pq with --descriptors)")
    p.add_argument("--ram-budget-mb", type=float, default=None, metavar="MB",
                   help="RAM budget of the searched vectors for --index auto")
    p.add_argument("--max-submap-size", type=int, default=None, metavar="N",
                   help="split submaps larger than N references into K-means sub-clusters "
                        "(bounds query time; default: no split)")
    p.add_argument("--rerank-factor", type=int, default=16, metavar="F",
                   help="pq: re-rank the top k*F PQ candidates exactly (default 16)")
    p.add_argument("--overwrite", action="store_true", help="replace a different existing map")
    add_descriptor_option_args(p)
    add_local_feature_args(p)
    add_engine_args(p)
    p.set_defaults(func=cmd_build_map)

    p = sub.add_parser("localize", help="localize query images against a map",
                       description="For each query: ask the prior, retrieve the top-p "
                                   "references in the submaps inside the prior's confidence "
                                   "region (plus a global top-p on maps up to 250k "
                                   "references), and fuse visual and prior evidence into a "
                                   "posterior with calibrated 68/95 % radii (default "
                                   "--fusion posterior; --fusion paper: the paper's nearest "
                                   "submap + re-rank by distance to the prior). "
                                   "docs/fusion.md.")
    p.add_argument("--map", required=True, metavar="MAP", help="map folder to localize on")
    p.add_argument("--images", metavar="DIR", help="folder of query images (optional with "
                   "--query-descriptors: then only given to a prior that needs pixels)")
    p.add_argument("--query-descriptors", metavar="Q.npy", default=None,
                   help="precomputed (n, dim) query descriptors, rows aligned with --queries: "
                        "no descriptor model or weights are loaded")
    p.add_argument("--queries", required=True, metavar="CSV", help="CSV with a 'file' column")
    p.add_argument("--out", required=True, metavar="RESULTS.csv",
                   help="results CSV, written row by row to RESULTS.csv.partial and renamed "
                        "when all queries are done")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true",
                   help="continue an interrupted run: keep the rows of RESULTS.csv(.partial), "
                        "localize the remaining (and failed) queries")
    g.add_argument("--overwrite", action="store_true",
                   help="replace an existing results CSV (kept until the new one is complete)")
    p.add_argument("--descriptor", default=None, metavar="NAME",
                   help="expected descriptor (error if the map was built with another)")
    add_descriptor_option_args(p)
    add_prior_args(p)
    add_localizer_args(p)
    add_verification_args(p)
    g = p.add_argument_group("inspection")
    g.add_argument("--save-matches", metavar="DIR", default=None,
                   help="write per query an image of the query beside its top candidates with "
                        "the verified inlier matches drawn (reference images: the map's own or "
                        "--reference-images)")
    g.add_argument("--only-wrong", action="store_true",
                   help="--save-matches only for answers more than 25 m from the truth")
    g.add_argument("--ground-truth", metavar="CSV", default=None,
                   help="file, lat, lon: colours the drawn matches green (right) / red (wrong)")
    p.set_defaults(func=cmd_localize)

    p = sub.add_parser("evaluate", help="accuracy of a results CSV against ground truth")
    p.add_argument("--results", required=True, metavar="RESULTS.csv",
                   help="results CSV written by 'vlm-vpr localize'")
    p.add_argument("--ground-truth", required=True, metavar="CSV",
                   help="file, lat, lon (or IMG_ID, LAT, LON)")
    p.add_argument("--json", action="store_true", help="print only a JSON object on stdout")
    add_integrity_args(p, "RESULTS_integrity/ beside the results CSV")
    p.add_argument("--geojson", metavar="OUT.geojson", default=None,
                   help="also write the results as GeoJSON (RFC 7946: [lon, lat] points, "
                        "with truth and error_km) for a GIS")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("descriptors", help="list the descriptor presets")
    p.set_defaults(func=cmd_descriptors)

    p = sub.add_parser("demo", help="the main job on the shipped demo data (start here)",
                       description="Builds a map from the 71 shipped OpenStreetView-5M images, "
                                   "localizes re-cropped and re-lit copies of them without a "
                                   "prior, with the recorded OSV-5M priors (default fusion and "
                                   "the paper's method) and the prior alone; repeats it on a "
                                   "look-alike map (every place also 5000 km away with the same "
                                   "image, built from the shipped images) where VPR alone cannot "
                                   "tell them apart; the default fusion is verified (fix rate and "
                                   "fix precision); then makes and evaluates a bag. Prints the "
                                   "tables, writes them to OUT/demo.json with an error CDF and a "
                                   "contact sheet. About 2 CPU-minutes (it prints its time).")
    p.add_argument("--out", default="demo_out", metavar="DIR", help="output folder")
    p.add_argument("--skip-bag", action="store_true", help="skip the bag part of the demo")
    p.set_defaults(func=cmd_demo)


def add_teach_args(p: argparse.ArgumentParser) -> None:
    """--bag and the teach-run options (build-map, map add)."""
    g = p.add_argument_group("teach run (references from a rosbag2 bag, MCAP or sqlite3)")
    g.add_argument("--bag", metavar="BAG", help="bag folder, .mcap or .db3 with a camera topic "
                   "and a sensor_msgs/NavSatFix topic (instead of --images/--coords)")
    g.add_argument("--image-topic", metavar="T", default=None,
                   help="Image or CompressedImage topic (default: the bag's only one)")
    g.add_argument("--fix-topic", metavar="T", default=None,
                   help="NavSatFix topic (default: the bag's only one)")
    g.add_argument("--fix-tolerance-s", type=float, default=0.5, metavar="S",
                   help="a frame needs a fix at most S seconds before and after it (default 0.5)")
    g.add_argument("--min-spacing-m", type=float, default=2.0, metavar="M",
                   help="keep a frame only M metres from the last kept one (default 2)")
    g.add_argument("--max-fix-sigma-m", type=float, default=10.0, metavar="M",
                   help="ignore fixes whose horizontal standard deviation exceeds M (default 10)")


def teach_config(args: argparse.Namespace):
    from vlm_vpr_ros.bags.teach import TeachConfig

    return TeachConfig(args.image_topic, args.fix_topic, args.fix_tolerance_s,
                       args.min_spacing_m, args.max_fix_sigma_m)


def check_source_args(args: argparse.Namespace) -> None:
    """Exactly one reference source: --bag, or --images (or --descriptors) with --coords."""

    descriptors = getattr(args, "descriptors", None)
    if descriptors and (args.images or args.bag):
        raise ConfigError("give --descriptors SRC or --images DIR or --bag BAG, not several")
    if descriptors:
        if not args.coords:
            raise ConfigError("--descriptors needs --coords CSV (file, lat, lon per row)")
        return
    if args.bag and (args.images or args.coords):
        raise ConfigError("give either --bag or --images/--coords, not both")
    if not args.bag and not (args.images and args.coords):
        raise ConfigError("give --images DIR and --coords CSV, or --bag BAG")


def cmd_build_map(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.mapping.build_images import build_map

    check_source_args(args)
    # the map is built beside --out and swapped in: never over or holding an input
    check_not_inside(args.out, [args.images, args.coords, args.bag,
                                getattr(args, "descriptors", None)], allow_out_inside=True)
    local = local_feature_options(args)
    if args.bag:
        from vlm_vpr_ros.bags.teach import build_map_from_bag

        if args.engine != "local":
            raise ConfigError("--engine ray builds from --images/--coords, not from --bag")
        m, res = build_map_from_bag(
            args.bag, args.out, teach_config(args), overwrite=args.overwrite,
            descriptor=args.descriptor, descriptor_config=descriptor_options(args),
            partition=args.partition, clusters=args.clusters, index=args.index or "flat",
            **local)
        print(res.describe())
        print(f"map {args.out}: {m.n_references} references, {len(m.submaps)} submaps "
              f"({m.partition_method}), descriptor {m.descriptor_identity['name']} "
              f"{m.dim}-D, images stored in the map")
        return 0
    sizing = {"ram_budget_mb": args.ram_budget_mb, "max_submap_size": args.max_submap_size,
              "rerank_factor": args.rerank_factor}
    if args.descriptors:
        from vlm_vpr_ros.mapping.build_descriptors import build_from_descriptors

        engine_options(args)  # Ray-only options without --engine ray are errors
        if args.engine == "ray":
            raise ConfigError("--descriptors builds out of core in this process; --engine ray "
                              "is for images (describe them with 'vlm-vpr describe')")
        if local["local_features"] != "none":
            raise ConfigError("--descriptors builds from precomputed descriptors: there are no "
                              "images to extract local features from (verify at query time "
                              "with --reference-images DIR; docs/verification.md)")
        m = build_from_descriptors(args.descriptors, args.coords, args.out, args.descriptor,
                                   descriptor_options(args), partition=args.partition,
                                   clusters=args.clusters, overwrite=args.overwrite,
                                   index=args.index or "pq", **sizing)
        skipped = len(m.manifest["source"].get("skipped", []))
        print(f"map {args.out}: {m.n_references} references ({skipped} skipped), "
              f"{len(m.submaps)} submaps ({m.partition_method}), index {m.manifest['index']}, "
              f"descriptor {m.descriptor_identity['name']} {m.dim}-D")
        return 0
    args.index = args.index or "flat"
    if args.engine == "ray":
        m = cmd_build_map_ray(args)
    else:
        engine_options(args)  # Ray-only options without --engine ray are errors
        m = build_map(args.images, args.coords, args.out, descriptor=args.descriptor,
                      descriptor_config=descriptor_options(args), partition=args.partition,
                      clusters=args.clusters, overwrite=args.overwrite, index=args.index,
                      calibration_conditions=_conditions(args), **local, **sizing)
    print(f"map {args.out}: {m.n_references} references, {len(m.submaps)} submaps "
          f"({m.partition_method}), descriptor {m.descriptor_identity['name']} "
          f"{m.dim}-D")
    return 0


def _conditions(args: argparse.Namespace):
    """build-map --calibration-conditions, checked before any work (ConfigError: exit 2)."""
    from vlm_vpr_ros.localization.verification.conditions import parse_conditions

    v = getattr(args, "calibration_conditions", None)
    return None if v is None else [c.name for c in parse_conditions(v)]


def cmd_descriptors(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.descriptors import available_descriptors

    for name, preset in available_descriptors().items():
        dim = preset.dim if preset.dim else "fitted"
        print(f"{name:<22}{dim!s:>8}  {preset.summary}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.evaluation.demo import run_demo

    return run_demo(args.out, with_bag=not args.skip_bag)
