"""``vlm-vpr map``: edit an existing map folder in place (``add``, ``remove``)."""

from __future__ import annotations

import argparse
import logging
import os
import shutil
from pathlib import Path

from vlm_vpr_ros.cli.common import add_descriptor_option_args, descriptor_options
from vlm_vpr_ros.cli.core import add_teach_args, check_source_args, teach_config

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="add references to or remove them from an existing map")
    msub = p.add_subparsers(dest="map_command", metavar="ACTION")
    msub.required = True

    a = msub.add_parser(
        "add", help="add references (images + CSV, or a teach bag) without rebuilding",
        description="Describes the new references with the map's own descriptor state "
                    "(codebook, PCA), puts each into the submap its position belongs to (a new "
                    "submap when none fits) and rewrites only those submaps; the manifest is "
                    "replaced last, so a failed add leaves the map as it was.")
    a.add_argument("map", metavar="MAP", help="map folder to grow")
    a.add_argument("--images", metavar="DIR", help="folder of the new reference images")
    a.add_argument("--coords", metavar="CSV", help="file (relative to DIR), lat, lon")
    add_teach_args(a)
    a.add_argument("--descriptor", default=None, metavar="NAME",
                   help="expected descriptor (refused if the map was built with another)")
    a.add_argument("--store-images", choices=["auto", "yes", "no"], default="auto",
                   help="copy the new images into the map (auto: when the map holds its "
                        "images, as teach maps do; a --bag's frames are always stored)")
    add_descriptor_option_args(a)
    a.set_defaults(func=cmd_map_add)

    r = msub.add_parser("remove", help="remove references by id",
                        description="Removes the listed references; affected submaps are "
                                    "rewritten, emptied ones dropped. Unknown ids change "
                                    "nothing.")
    r.add_argument("map", metavar="MAP")
    r.add_argument("--ids", required=True, metavar="FILE",
                   help="one reference id per line (# comments allowed), or a CSV with a "
                        "'file' column")
    r.set_defaults(func=cmd_map_remove)


def cmd_map_add(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.map_build import read_coords_csv
    from vlm_vpr_ros.map_edit import add_references

    check_source_args(args)
    store = {"auto": None, "yes": True, "no": False}[args.store_images]
    opts = dict(descriptor=args.descriptor, descriptor_config=descriptor_options(args))
    if not args.bag:
        rows = read_coords_csv(args.coords)
        res = add_references(args.map, args.images, rows, store_images=store,
                             source={"images": str(args.images), "coords": str(args.coords)},
                             **opts)
        print(res.describe())
        return 0
    from vlm_vpr_ros.bags.teach import extract_references

    stage = Path(args.map) / f".add{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    try:
        teach = extract_references(args.bag, stage, teach_config(args))
        print(teach.describe())
        rows = [(r.id, r.lat, r.lon) for r in teach.references]
        res = add_references(args.map, stage, rows, store_images=store is not False,
                             move_images=True, source={"bag": str(args.bag),
                                                       **teach.summary()}, **opts)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    print(res.describe())
    return 0


def cmd_map_remove(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.map_edit import read_ids_file, remove_references

    ids = read_ids_file(args.ids)
    res = remove_references(args.map, ids, source={"ids_file": str(args.ids)})
    print(res.describe())
    return 0
