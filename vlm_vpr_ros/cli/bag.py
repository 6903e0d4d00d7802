"""Bag sub-commands: ``bag make``/``bag info``, ``replay``, ``evaluate-bag`` and ``ablate``."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from vlm_vpr_ros.cli.common import (add_descriptor_option_args, add_localizer_args,
                                    add_prior_args, descriptor_options, localizer_config,
                                    make_prior_provider, prior_inputs)
from vlm_vpr_ros.cli.evaluate import add_integrity_args

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bag", help="make or inspect rosbag2 bags (MCAP, sqlite3)")
    bsub = p.add_subparsers(dest="bag_command", metavar="ACTION")
    bsub.required = True
    m = bsub.add_parser("make", help="geotagged images -> rosbag2 MCAP (camera + NavSatFix)",
                        description="Writes one camera frame per CSV row at --rate, each with a "
                                    "sensor_msgs/NavSatFix ground truth of the same stamp, as a "
                                    "rosbag2 bag folder (MCAP or sqlite3, metadata.yaml; "
                                    "frames.csv beside).")
    m.add_argument("--images", required=True, metavar="DIR",
                   help="folder of the images named in --coords")
    m.add_argument("--coords", required=True, metavar="CSV", help="columns file, lat, lon")
    m.add_argument("--out", required=True, metavar="BAG", help="bag folder to create")
    m.add_argument("--rate", type=float, default=1.0, metavar="HZ", help="frames per second")
    m.add_argument("--compressed", action="store_true",
                   help="sensor_msgs/CompressedImage (JPEG/PNG stored as is) instead of raw "
                        "rgb8 sensor_msgs/Image")
    m.add_argument("--topic-prefix", default="/camera", metavar="NS",
                   help="image topic is NS/image_raw[/compressed] (default /camera)")
    m.add_argument("--gt-topic", default="/gps/fix", metavar="TOPIC",
                   help="sensor_msgs/NavSatFix ground-truth topic (default /gps/fix)")
    m.add_argument("--frame-id", default="camera", metavar="ID",
                   help="header.frame_id of the image messages (default camera)")
    m.add_argument("--start-time", default=None, metavar="SEC[.NANOSEC]",
                   help="stamp of the first frame, seconds since the epoch, read exactly (up "
                        "to 9 decimals; default: now)")
    m.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap",
                   help="rosbag2 storage: BAG/BAG.mcap (default) or BAG/BAG.db3")
    m.add_argument("--mcap-compression", choices=["none", "zstd"], default="none",
                   help="MCAP chunk compression (default none; zstd needs --storage mcap)")
    m.add_argument("--overwrite", action="store_true",
                   help="replace an existing bag folder (kept until the new one is complete)")
    m.set_defaults(func=cmd_bag_make)
    i = bsub.add_parser("info", help="topics, types and counts of a bag")
    i.add_argument("bag", metavar="BAG", help="bag folder, .mcap or .db3")
    i.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    i.set_defaults(func=cmd_bag_info)

    r = sub.add_parser("replay", help="publish a bag's messages on live ROS 2 topics",
                       description="Publishes the recorded CDR messages through rclpy with "
                                   "their recorded relative timing (divided by --rate).")
    r.add_argument("bag", metavar="BAG", help="bag folder, .mcap or .db3")
    r.add_argument("--rate", type=float, default=1.0, metavar="X", help="speed factor")
    r.add_argument("--loop", action="store_true", help="start over at the end (Ctrl-C stops)")
    r.add_argument("--topics", nargs="+", default=None, metavar="T", help="only these topics")
    r.add_argument("--remap", action="append", default=[], metavar="FROM:=TO",
                   help="publish topic FROM as TO (repeatable)")
    r.add_argument("--wait-subscribers", type=float, default=5.0, metavar="S",
                   help="wait up to S seconds for a subscriber on every topic (default 5)")
    r.add_argument("--domain-id", type=int, default=None, metavar="N",
                   help="ROS domain (default: ROS_DOMAIN_ID)")
    r.add_argument("--clock", nargs="?", type=float, const=100.0, default=None, metavar="HZ",
                   help="publish /clock (rosgraph_msgs/Clock) from the bag's log times at HZ "
                        "(default 100) for nodes with use_sim_time")
    r.set_defaults(func=cmd_replay)

    e = sub.add_parser("evaluate-bag", help="localize a bag's frames offline and score them",
                       description="Reads images and NavSatFix ground truth from the bag, "
                                   "localizes every frame (default --fusion posterior, as the "
                                   "node), writes frames.csv, summary.json, world_map.png, "
                                   "error_cdf.png, the integrity report (integrity.json, "
                                   "stanford.png) and an estimates bag.")
    e.add_argument("bag", metavar="BAG", help="bag folder, .mcap or .db3")
    e.add_argument("--map", required=True, metavar="MAP", help="map folder to localize on")
    _frame_args(e)
    e.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default: BAG_eval next to the bag)")
    e.add_argument("--overwrite", action="store_true",
                   help="replace an earlier evaluation folder (kept until the new one is "
                        "complete)")
    e.add_argument("--no-plots", action="store_true",
                   help="skip world_map.png and error_cdf.png")
    e.add_argument("--json", action="store_true", help="print only a JSON object on stdout")
    add_integrity_args(e, None)
    add_descriptor_option_args(e)
    add_prior_args(e)
    add_localizer_args(e)
    e.set_defaults(func=cmd_evaluate_bag)

    a = sub.add_parser("ablate", help="the paper's ablation table and top-p plot",
                       description="Rows {no prior, prior+re-rank, country submap, cluster "
                                   "submap (each with/without re-rank)} of the paper's method, "
                                   "plus the default posterior fusion with and without the "
                                   "prior, x a top-p sweep, from one map (re-partitioned in "
                                   "memory).")
    a.add_argument("--map", required=True, metavar="MAP", help="map folder to ablate on")
    a.add_argument("--images", metavar="DIR", help="query images (with --queries)")
    a.add_argument("--queries", metavar="CSV", help="query file, lat, lon")
    a.add_argument("--bag", metavar="BAG", help="or: take the queries from a bag")
    _frame_args(a)
    a.add_argument("--top-p", default="1,5,10,25,50,100", metavar="LIST",
                   help="comma-separated top-p sweep (default 1,5,10,25,50,100)")
    a.add_argument("--clusters", type=int, default=None, metavar="K",
                   help="K of the cluster submaps (default: the map's K, or 100)")
    a.add_argument("--table-top-p", type=int, default=None, metavar="P",
                   help="top-p of the main table (default: the largest swept)")
    a.add_argument("--metric", default="25km", help="threshold of the sweep table")
    a.add_argument("--out", default="ablation_out", metavar="DIR",
                   help="output folder (default ablation_out)")
    a.add_argument("--json", action="store_true", help="print only a JSON object on stdout")
    add_descriptor_option_args(a)
    add_prior_args(a)
    a.set_defaults(func=cmd_ablate)


def _frame_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--image-topic", default=None, metavar="T",
                   help="Image/CompressedImage topic (default: the bag's only one)")
    p.add_argument("--gt-topic", default=None, metavar="T",
                   help="NavSatFix ground-truth topic (default: the bag's only one)")
    p.add_argument("--max-gt-gap", type=float, default=0.5, metavar="S",
                   help="pair a frame with a fix at most S seconds away (default 0.5)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="only the first N frames (default: all)")


def parse_stamp(text: str, what: str) -> int:
    """``SEC`` or ``SEC.FRACTION`` (≤ 9 digits) → integer ns, exactly (no float on the way)."""
    import decimal

    from vlm_vpr_ros.errors import ConfigError

    try:
        value = decimal.Decimal(str(text).strip())
    except decimal.InvalidOperation:
        raise ConfigError(f"{what}: expected seconds such as 1700000000.5, got {text!r}") \
            from None
    ns = value * 1_000_000_000
    if not value.is_finite() or value < 0 or ns != ns.to_integral_value():
        raise ConfigError(f"{what}: expected non-negative seconds with at most 9 decimals, "
                          f"got {text!r}")
    return int(ns)


def cmd_bag_make(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.bags.make import make_bag

    start = None if args.start_time is None else parse_stamp(args.start_time, "--start-time")
    info = make_bag(args.images, args.coords, args.out, rate_hz=args.rate,
                    compressed=args.compressed, topic_prefix=args.topic_prefix,
                    gt_topic=args.gt_topic, frame_id=args.frame_id, start_time_ns=start,
                    storage=args.storage, compression=args.mcap_compression,
                    overwrite=args.overwrite)
    print(f"bag {info['bag']}: {info['frames']} frames on {info['image_topic']} + "
          f"{info['gt_topic']} over {info['duration_s']:.1f} s"
          + (f" ({len(info['skipped'])} unreadable images skipped)" if info["skipped"] else ""))
    return 0


def cmd_bag_info(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.bags.reader import open_bag

    bag = open_bag(args.bag)
    topics = {t.name: {"type": t.type, "count": t.count} for t in bag.topics.values()}
    if args.json:
        json.dump({"path": str(bag.path), "storage": bag.storage, "topics": topics,
                   "complete": bag.complete, "problems": bag.problems}, sys.stdout)
        sys.stdout.write("\n")
        return 0
    print(f"{bag.path} ({bag.storage}, {len(bag.files)} file(s))")
    for name, t in sorted(topics.items()):
        print(f"  {name:<40} {t['type']:<40} {t['count'] if t['count'] is not None else '?':>8}")
    for p in bag.problems:
        print(f"  problem: {p}")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from vlm_vpr_ros.bags.reader import open_bag
    from vlm_vpr_ros.bags.replay import ReplayConfig, parse_remaps, replay_bag

    bag = open_bag(args.bag)
    cfg = ReplayConfig(rate=args.rate, loop=args.loop, topics=args.topics,
                       remap=parse_remaps(args.remap), wait_subscribers_s=args.wait_subscribers,
                       domain_id=args.domain_id, clock_hz=args.clock)
    bar = tqdm(desc="replay", unit="msg", disable=None, leave=False)

    def progress(done: int, total: int, t: float) -> None:
        if bar.total != total:
            bar.reset(total=total)
        bar.n = done
        bar.set_postfix_str(f"bag t={t:.1f}s", refresh=False)
        bar.refresh() if done == total else bar.update(0)

    try:
        stats = replay_bag(bag, cfg, progress)
    finally:
        bar.close()
    print(f"replayed {stats['published']} messages on {len(stats['topics'])} topic(s) in "
          f"{stats.get('wall_s', 0):.1f} s ({stats['loops']} pass(es))")
    return 0


def cmd_evaluate_bag(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.bags.evaluate import BagEvalConfig, evaluate_bag
    from vlm_vpr_ros.bags.reader import open_bag
    from vlm_vpr_ros.evaluation.metrics import format_table
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

    from vlm_vpr_ros.bags.messages import IMAGE_TYPES, NAVSATFIX

    from vlm_vpr_ros.evaluation.integrity import check_alert_limit
    from vlm_vpr_ros.evaluation.integrity_tables import format_report

    alert_m = check_alert_limit(args.alert_limit_m)
    bag = open_bag(args.bag)
    bag.find_topic(IMAGE_TYPES, args.image_topic, "camera images")  # fail before loading
    bag.find_topic((NAVSATFIX,), args.gt_topic, "ground truth")
    out = Path(args.out) if args.out else Path(str(Path(args.bag)).rstrip("/") + "_eval")
    from vlm_vpr_ros.files.outputs import check_not_inside, check_target

    # fail before loading the map; never holding an input (a swap would drop it)
    check_not_inside(out, [bag.path, args.map, *prior_inputs(args)])
    check_target(out, "evaluation", args.overwrite)
    provider = make_prior_provider(args)  # a bad priors CSV or option: exit 2 before the map
    try:
        pipe = LocalizationPipeline.open(args.map, localizer=localizer_config(args),
                                         descriptor_config=descriptor_options(args))
        pipe.map.open_submaps()  # a damaged map: exit 2 before the first frame
        cfg = BagEvalConfig(image_topic=args.image_topic, gt_topic=args.gt_topic,
                            max_gt_gap_s=args.max_gt_gap, max_frames=args.max_frames,
                            prior_timeout_s=args.prior_timeout, alert_limit_m=alert_m)
        res = evaluate_bag(bag, pipe, provider, out, cfg, plots=not args.no_plots,
                           overwrite=args.overwrite)
    finally:
        provider.close()
    if args.json:
        json.dump(res, sys.stdout)
        sys.stdout.write("\n")
        return 0
    d = res["details"]
    print(format_table({"estimate": res}, title=f"evaluate-bag {bag.path}: {d['frames']} "
                       f"frames, {d['frames_scored']} with ground truth"))
    print("\n" + format_report(res["integrity"], "integrity (docs/evaluation.md)"))
    for key, path in d["outputs"].items():
        print(f"{key:>14}: {path}")
    for w in d["warnings"]:
        print(f"warning: {w}")
    return 0


def cmd_ablate(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.evaluation.ablation import ablation_table, format_ablation, run_ablation
    from vlm_vpr_ros.evaluation.metrics import table_cells
    from vlm_vpr_ros.bags.ablate_inputs import ablation_inputs
    from vlm_vpr_ros.config import choose
    from vlm_vpr_ros.files.atomic import atomic_write_json
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.evaluation.plots import plot_topp_ablation

    try:
        top_ps = [int(x) for x in args.top_p.split(",") if x.strip()]
    except ValueError:
        from vlm_vpr_ros.errors import ConfigError

        raise ConfigError(f"--top-p must be comma-separated integers, got {args.top_p!r}") \
            from None
    choose(args.metric, {f"{t:g}km": 1 for t in (1, 25, 200, 750, 2500)}, "metric")
    out = Path(args.out)
    _check_ablation_out(out, [args.map, args.bag],
                        [args.images, args.queries, *prior_inputs(args)])
    provider = make_prior_provider(args)  # a bad priors CSV or option: exit 2 before the map
    try:
        pipe = LocalizationPipeline.open(args.map, descriptor_config=descriptor_options(args))
        pipe.map.open_submaps()
        desc, truth, priors = ablation_inputs(args, pipe, provider)
    finally:
        provider.close()
    res = run_ablation(pipe.map, desc, truth, priors, top_ps, clusters=args.clusters,
                       progress=lambda s: log.debug("ablation: %s", s))
    out.mkdir(parents=True, exist_ok=True)
    plot = plot_topp_ablation(out / "ablation_top_p.png", res.top_ps,
                              {k: [s["accuracy"] for s in v] for k, v in res.rows.items()},
                              title=f"top-p ablation ({len(desc)} queries)")
    title, _, table = ablation_table(res, args.table_top_p)
    head, body = table_cells(table)
    data = {**res.as_dict(), "plot": str(plot),  # "tables": what scripts/gen_docs.py renders
            "tables": {"main": {"title": title, "columns": head, "rows": body}}}
    atomic_write_json(out / "ablation.json", data)
    if args.json:
        json.dump(data, sys.stdout)
        sys.stdout.write("\n")
        return 0
    print(format_ablation(res, args.table_top_p, args.metric))
    print(f"\nplot: {plot}\njson: {out / 'ablation.json'}")
    return 0


def _is_ablation_json(path: Path) -> bool:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and {"top_p", "rows", "tables"} <= set(data)


def _check_ablation_out(out: Path, folders: list, files: list) -> None:
    """Before any work: ``ablate --out`` is no input (nor in the map or the bag, nor holds
    one) and its two files are new or an earlier ablation's
    (:func:`~vlm_vpr_ros.files.outputs.check_file_output`)."""
    from vlm_vpr_ros.files.outputs import check_file_output, check_not_inside

    check_not_inside(out, folders)
    check_not_inside(out, files, allow_out_inside=True)
    inputs = [i for i in folders + files if i]
    js = out / "ablation.json"
    check_file_output(js, "--out", inputs, _is_ablation_json, "an ablation.json")
    check_file_output(out / "ablation_top_p.png", "--out", inputs,
                      lambda p: _is_ablation_json(js), "an ablation plot")
