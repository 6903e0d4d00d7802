"""``vlm-vpr map``: edit a map folder in place (``add``, ``remove``; docs/teach.md), inspect,
verify and upgrade it (``info``, ``verify``, ``upgrade``; docs/planet_scale.md)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys
from pathlib import Path

from vlm_vpr_ros.cli.common import add_descriptor_option_args, descriptor_options
from vlm_vpr_ros.cli.core import add_teach_args, check_source_args, teach_config

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="add/remove references; info, verify or upgrade a map")
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
    r.add_argument("map", metavar="MAP", help="map folder to shrink")
    r.add_argument("--ids", required=True, metavar="FILE",
                   help="one reference id per line (# comments allowed), or a CSV with a "
                        "'file' column")
    r.set_defaults(func=cmd_map_remove)


    q = msub.add_parser("info", help="counts, submap sizes and index kinds, disk and RAM",
                        description="Reads only the manifest and file sizes (fast at any scale).")
    q.add_argument("map", metavar="MAP", help="map folder")
    q.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    q.set_defaults(func=cmd_info)

    q = msub.add_parser("verify", help="check the sha256 of every file against the manifest",
                        description="The full integrity pass: every byte against its "
                                    "sha256 (opening a map checks sizes, small files whole "
                                    "and sampled pages of the large ones).")
    q.add_argument("map", metavar="MAP", help="map folder")
    q.set_defaults(func=cmd_verify)

    q = msub.add_parser("upgrade", help="convert a map to format v2 (optionally another index)",
                        description="Writes a new v2 map folder beside the old one (never over "
                                    "it): memory-mapped, lazily opened submaps.")
    q.add_argument("map", metavar="MAP", help="map folder to convert (left as it is)")
    q.add_argument("--out", required=True, metavar="NEW_MAP", help="folder to write (must not "
                   "exist)")
    q.add_argument("--index", choices=["flat", "fp16", "pq"], default=None,
                   help="index kind of the new map (default: keep the old one)")
    q.add_argument("--rerank-factor", type=int, default=None, metavar="F",
                   help="pq: re-rank the top k*F PQ candidates exactly (default: the old map's)")
    q.set_defaults(func=cmd_upgrade)

def cmd_map_add(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv
    from vlm_vpr_ros.mapping.edit import add_references

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
    from vlm_vpr_ros.maps.format import read_manifest

    read_manifest(Path(args.map))  # a map, before any folder is made beside it
    # the frames are extracted beside the map (not into it: a rebuild that swaps the map
    # folder meanwhile would take them away); inside only when the parent is read-only
    target = Path(args.map)
    stage = target.parent / f".{target.name}.add{os.getpid()}"
    try:
        shutil.rmtree(stage, ignore_errors=True)
        stage.mkdir(parents=True)
    except PermissionError:
        stage = target / f".add{os.getpid()}"
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
    from vlm_vpr_ros.mapping.edit import read_ids_file, remove_references

    ids = read_ids_file(args.ids)
    res = remove_references(args.map, ids, source={"ids_file": str(args.ids)})
    print(res.describe())
    return 0


def map_info(path: str | Path) -> dict:
    """Summary of a map from its manifest and file sizes (no index is read)."""
    from vlm_vpr_ros.maps.indexes import ram_bytes
    from vlm_vpr_ros.maps.format import read_manifest

    path = Path(path)
    man = read_manifest(path)
    dim = int(man["descriptor"]["dim"])
    default_kind = man.get("index", "flat")
    subs = []
    for e in man["submaps"]:
        kind = e.get("kind", default_kind)
        disk = sum(int(man["files"].get(r, {}).get("bytes", 0)) for r in e["files"].values())
        subs.append({"id": e["id"], "group": e.get("group", e["id"]), "count": int(e["count"]),
                     "kind": kind, "disk_bytes": disk,
                     "ram_bytes": ram_bytes(kind, int(e["count"]), dim),
                     "recall": e.get("recall")})
    counts = [s["count"] for s in subs] or [0]
    kinds: dict[str, int] = {}
    for s in subs:
        kinds[s["kind"]] = kinds.get(s["kind"], 0) + 1
    return {
        "path": str(path), "version": man["version"], "descriptor": man["descriptor"]["name"],
        "dim": dim, "n_references": man["n_references"], "n_submaps": len(subs),
        "partition": man["partition"], "index": man.get("index", "flat"),
        "index_kinds": kinds, "index_params": man.get("index_params", {}),
        "submap_size": {"min": min(counts), "median": sorted(counts)[len(counts) // 2],
                        "max": max(counts)},
        "disk_bytes": sum(int(m.get("bytes", 0)) for m in man["files"].values()),
        "expected_ram_bytes": sum(s["ram_bytes"] for s in subs) if man["version"] >= 2
        else sum(s["disk_bytes"] for s in subs),
        "skipped": len(man.get("source", {}).get("skipped", [])),
        "local_features": _local_features_info(man),
        "submaps": subs,
    }


def _local_features_info(man: dict) -> dict | None:
    """The stored local features (docs/verification.md): feature, bytes per reference, the
    leave-one-out calibration of p_correct; None when the map stores none."""
    sec = man.get("local_features")
    if not sec:
        return None
    n = max(1, int(man.get("n_references", 0)))
    return {"preset": sec.get("preset"), "feature": (sec.get("feature") or {}).get("name"),
            "max_keypoints": sec.get("max_keypoints"), "bytes": int(sec.get("bytes", 0)),
            "bytes_per_reference": round(int(sec.get("bytes", 0)) / n),
            "keypoints_per_reference": round(int(sec.get("n_keypoints", 0)) / n, 1),
            "calibrated": bool(man.get("verification_calibration"))}


def _mb(b: int) -> str:
    return f"{b / 2 ** 20:,.1f} MiB"


def cmd_info(args: argparse.Namespace) -> int:
    info = map_info(args.map)
    if args.json:
        json.dump(info, sys.stdout)
        sys.stdout.write("\n")
        return 0
    s = info["submap_size"]
    print(f"map {info['path']} (format v{info['version']})")
    print(f"  descriptor   {info['descriptor']} {info['dim']}-D")
    print(f"  references   {info['n_references']:,} ({info['skipped']} skipped at build)")
    print(f"  submaps      {info['n_submaps']} ({info['partition']['method']}); size min "
          f"{s['min']:,} / median {s['median']:,} / max {s['max']:,}")
    kinds = ", ".join(f"{k}: {n}" for k, n in sorted(info["index_kinds"].items()))
    print(f"  index        {info['index']} ({kinds}); "
          f"rerank_factor {info['index_params'].get('rerank_factor', '-')}")
    print(f"  on disk      {_mb(info['disk_bytes'])}")
    lf = info["local_features"]
    if lf is None:
        print("  local feat.  none (answers unverified unless reference images are given; "
              "docs/verification.md)")
    else:
        print(f"  local feat.  {lf['preset']} ({lf['feature']}, <= {lf['max_keypoints']} "
              f"keypoints): {lf['bytes_per_reference'] / 1e3:.1f} kB per reference "
              f"({lf['keypoints_per_reference']:.0f} keypoints), {_mb(lf['bytes'])}; p_correct "
              + ("calibrated by leave-one-out" if lf["calibrated"] else "uncalibrated"))
    print(f"  RAM (hot)    {_mb(info['expected_ram_bytes'])} when every submap has been "
          "searched" + (" (v1: loaded whole)" if info["version"] < 2 else ""))
    print(f"  {'submap':<14}{'group':<10}{'refs':>10}  {'kind':<5}{'disk':>14}{'RAM':>14}"
          f"  recall@1/@50")
    for sub in info["submaps"]:
        r = sub["recall"]
        rec = f"{r['recall_at_1']:.3f}/{r['recall_at_50']:.3f}" if r else "exact"
        print(f"  {sub['id']:<14}{sub['group']:<10}{sub['count']:>10,}  {sub['kind']:<5}"
              f"{_mb(sub['disk_bytes']):>14}{_mb(sub['ram_bytes']):>14}  {rec}")
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from vlm_vpr_ros.maps.format import read_manifest, verify_files

    path = Path(args.map)
    man = read_manifest(path)
    total = sum(int(m.get("bytes", 0)) for m in man["files"].values())
    with tqdm(total=len(man["files"]), desc="verify", unit="file", disable=None) as bar:
        checked = verify_files(path, man, progress=lambda rel: bar.update(1))
    print(f"map {path}: OK ({len(checked)} files, {_mb(total)}, sha256 match the manifest)")
    return 0


def cmd_upgrade(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.errors import MapError
    from vlm_vpr_ros.files.lock import WriterLock
    from vlm_vpr_ros.files.outputs import StagedOutput, check_not_inside
    from vlm_vpr_ros.mapping.build_descriptors import convert_map
    from vlm_vpr_ros.maps.documents import carry_companions
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    out = Path(args.out)
    if out.exists():
        raise MapError(f"{out} exists; upgrade writes a new folder beside the old map")
    check_not_inside(out, [args.map])
    # the source's writer lock: no edit or rebuild swaps it while it is read
    with WriterLock(args.map, "map upgrade (reading it)", inside_ok=True):
        old = ReferenceMap.load(args.map, verify=True)
        kind = args.index or old.manifest.get("index", "flat")
        new = convert_map(old, "pq" if kind == "auto" else kind,
                          args.rerank_factor or old.rerank_factor)
        with StagedOutput(out, "map") as stage:  # the new map's lock, staged then swapped in
            new.save(stage.path)
            # same submaps, same rows: calibrations, local features and images stay valid
            carried = carry_companions(Path(args.map), old.manifest, stage.path)
            stage.commit(validate=ReferenceMap.load)
    print(f"map {args.out}: v2, {new.n_references} references, {len(new.submaps)} submaps, "
          f"index {kind} (from {args.map}, format v{old.manifest['version']}); "
          f"{len(carried)} other files carried (calibrations, local features, images)")
    return 0
