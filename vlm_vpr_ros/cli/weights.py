"""``vlm-vpr weights``: list, locate, fetch and check the checkpoints of the deep VPR models."""

from __future__ import annotations

import argparse
import json

from vlm_vpr_ros.descriptors.deep.specs import MODEL_SPECS, get_spec


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("weights", help="checkpoints of the deep VPR models (list/path/fetch)",
                       description="The deep descriptors load the official checkpoints from "
                                   "--weights PATH or from $TORCH_HOME/hub/checkpoints.")
    wsub = p.add_subparsers(dest="weights_command", metavar="ACTION")
    wsub.required = True
    names = ", ".join(MODEL_SPECS)

    q = wsub.add_parser("list", help="models, official files and whether they are present")
    q.add_argument("--json", action="store_true", help="print one JSON object")
    q.set_defaults(func=cmd_list)

    q = wsub.add_parser("path", help="print where the loader looks for MODEL's checkpoint")
    q.add_argument("model", metavar="MODEL", help=names)
    q.set_defaults(func=cmd_path)

    q = wsub.add_parser("fetch", help="download official checkpoints (needs internet)",
                        description="Download from the official release URL (GitHub release "
                                    "or the Google Drive file of the MixVPR README), check that "
                                    "the file fits the model, store it atomically.")
    q.add_argument("models", nargs="+", metavar="MODEL", help=f"{names}, or 'all'")
    q.add_argument("--dest", metavar="DIR", default=None,
                   help="store here instead of $TORCH_HOME/hub/checkpoints (then pass "
                        "--weights DIR/FILE when building maps)")
    q.add_argument("--url", default=None, help="download from this URL instead (one MODEL)")
    q.add_argument("--force", action="store_true", help="download even if the file exists")
    q.set_defaults(func=cmd_fetch)

    q = wsub.add_parser("check", help="load a checkpoint into MODEL (strict) and print its hash")
    q.add_argument("model", metavar="MODEL", help=names)
    q.add_argument("--weights", metavar="PATH", default=None,
                   help="checkpoint file (default: the torch hub cache)")
    q.add_argument("--json", action="store_true", help="print one JSON object")
    q.set_defaults(func=cmd_check)


def cmd_list(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.descriptors.deep.weights import describe_weights

    rows = [describe_weights(spec) for spec in MODEL_SPECS.values()]
    if args.json:
        print(json.dumps({"models": rows}))
        return 0
    print(f"{'model':<13}{'dim':>6}  {'present':<8}path")
    for r in rows:
        print(f"{r['model']:<13}{r['dim']:>6}  {'yes' if r['present'] else 'no':<8}{r['path']}")
    return 0


def cmd_path(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.descriptors.deep.weights import default_weights_path

    print(default_weights_path(get_spec(args.model)))
    return 0


def cmd_fetch(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.descriptors.deep.weights import fetch
    from vlm_vpr_ros.errors import ConfigError

    names = list(MODEL_SPECS) if args.models == ["all"] else args.models
    specs = [get_spec(n) for n in names]
    if args.url and len(specs) != 1:
        raise ConfigError("--url needs exactly one MODEL")
    for spec in specs:
        path = fetch(spec, dest=args.dest, url=args.url, force=args.force)
        print(f"{spec.name}: {path}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.descriptors.deep import weights as W

    spec = get_spec(args.model)
    path = W.resolve_weights(spec, args.weights)
    W.load_weights(W.build_model(spec), path, spec.name)
    result = {"model": spec.name, "path": str(path), "ok": True, "sha256": W.file_sha256(path)}
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{spec.name}: {path} loads (strict), sha256 {result['sha256']}")
    return 0
