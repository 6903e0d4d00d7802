"""``vlm-vpr describe`` and the engine options of ``build-map`` (``--engine ray``)."""

from __future__ import annotations

import argparse

from vlm_vpr_ros.cli.common import add_descriptor_option_args, descriptor_options


def add_engine_args(parser: argparse.ArgumentParser) -> None:
    """--engine local|ray and the Ray options (shared by describe and build-map)."""
    from vlm_vpr_ros.distributed.shards import DEFAULT_SHARD_SIZE

    g = parser.add_argument_group("engine (see docs/ray.md)")
    g.add_argument("--engine", choices=["local", "ray"], default="local",
                   help="local: this process (default); ray: a Ray actor pool, on this "
                        "machine or on the cluster of --ray-address")
    g.add_argument("--ray-address", metavar="ADDR", default=None,
                   help="auto, HOST:PORT (a cluster's GCS) or ray://HOST:PORT (Ray Client); "
                        "default: start a Ray on this machine")
    g.add_argument("--workers", type=int, default=None, metavar="N",
                   help="describing actors (default: one per CPU, or per GPU share)")
    g.add_argument("--batch-size", type=int, default=16, metavar="N",
                   help="images per batch sent to a worker (and per GPU forward pass)")
    g.add_argument("--num-gpus-per-worker", type=float, default=0.0, metavar="X",
                   help="GPUs per actor (e.g. 1, or 0.5 to share a GPU); deep models then "
                        "run on the GPU in batches of --batch-size")
    g.add_argument("--fit-on", choices=["driver", "cluster"], default="driver",
                   help="where vlad_rootsift learns its codebook/PCA from the sample: driver "
                        "(default; identical to the local build) or cluster (one Ray task, "
                        "for drivers that cannot read the images)")
    g.add_argument("--shard-size", type=int, default=DEFAULT_SHARD_SIZE, metavar="N",
                   help=f"images per descriptor shard; the unit of resuming (default "
                        f"{DEFAULT_SHARD_SIZE})")


def engine_options(args: argparse.Namespace):
    from vlm_vpr_ros.distributed.describe import DescribeOptions

    opts = DescribeOptions(engine=args.engine, ray_address=args.ray_address,
                           workers=args.workers, batch_size=args.batch_size,
                           num_gpus_per_worker=args.num_gpus_per_worker,
                           shard_size=args.shard_size, fit_on=args.fit_on)
    opts.validate()
    return opts


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("describe", help="describe reference images into descriptor shards",
                       description="Describe every reference image (locally or on a Ray "
                                   "cluster) into SHARDS/: shard_*.npy + .ids.txt, "
                                   "describe.json and the fitted descriptor_state.npz. "
                                   "Resumable: finished shards are kept. Build the map with "
                                   "'build-map --descriptors SHARDS/'.")
    p.add_argument("--images", required=True, metavar="DIR|URI",
                   help="folder of reference images, or a file:// s3:// gs:// URI")
    p.add_argument("--coords", required=True, metavar="CSV",
                   help="CSV with columns file (relative to DIR), lat, lon")
    p.add_argument("--out", required=True, metavar="SHARDS", help="shard folder to write")
    p.add_argument("--descriptor", default="vlad_rootsift", metavar="NAME",
                   help="descriptor preset (see 'vlm-vpr descriptors'; default vlad_rootsift)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a shard folder written by 'vlm-vpr describe' that holds "
                        "other descriptors (kept until the new one is complete; any other "
                        "folder is never replaced)")
    add_descriptor_option_args(p)
    add_engine_args(p)
    p.set_defaults(func=cmd_describe)


def cmd_describe(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.distributed.describe import describe_to_shards
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv

    opts = engine_options(args)
    rows = read_coords_csv(args.coords)
    res = describe_to_shards(args.images, [r[0] for r in rows], args.out,
                             descriptor=args.descriptor,
                             descriptor_config=descriptor_options(args), options=opts,
                             overwrite=args.overwrite, inputs=[args.coords])
    print(res.summary())
    return 0


def cmd_build_map_ray(args: argparse.Namespace):
    """``build-map --engine ray``; returns the ReferenceMap."""
    from vlm_vpr_ros.cli.common import local_feature_options
    from vlm_vpr_ros.distributed.build import build_map_ray

    return build_map_ray(args.images, args.coords, args.out, descriptor=args.descriptor,
                         descriptor_config=descriptor_options(args), partition=args.partition,
                         clusters=args.clusters, overwrite=args.overwrite, index=args.index,
                         options=engine_options(args), **local_feature_options(args))
