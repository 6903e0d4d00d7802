"""Argument groups shared by the sub-commands (priors, localizer switches, descriptor options,
verification and status)."""

from __future__ import annotations

import argparse

from vlm_vpr_ros.config import parse_kv
from vlm_vpr_ros.localization.localizer import FUSION_MODES, LocalizerConfig
from vlm_vpr_ros.localization.verification.stage import VerificationConfig
from vlm_vpr_ros.localization.verification.status import StatusPolicy
from vlm_vpr_ros.priors import PriorProvider, available_prior_providers, create_prior_provider


def add_prior_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("prior (coarse position guess)")
    g.add_argument("--prior", metavar="NAME", default=None,
                   help="prior provider: " + ", ".join(available_prior_providers())
                   + " (default: none, or recorded with --priors)")
    g.add_argument("--prior-option", metavar="KEY=VALUE", action="append", default=[],
                   help="provider setting, repeatable (e.g. lat=48.85 lon=2.35 for 'fixed'; "
                        "base_url=... model=... for 'openai'; path=... for 'answers')")
    g.add_argument("--priors", metavar="CSV", default=None,
                   help="shortcut for --prior recorded --prior-option path=CSV "
                        "(columns file, lat, lon)")
    g.add_argument("--prior-timeout", type=float, default=60.0, metavar="S",
                   help="give up on a prior after S seconds (flagged fallback)")


def make_prior_provider(args: argparse.Namespace) -> PriorProvider:
    options = parse_kv(args.prior_option)
    name = args.prior
    if args.priors:
        name = name or "recorded"
        options.setdefault("path", args.priors)
    return create_prior_provider(name or "none", options)


def prior_inputs(args: argparse.Namespace) -> list[str]:
    """The files a prior provider reads (``--priors``, ``--prior-option path=``): inputs that
    no output of the command may be, replace or hold."""
    path = parse_kv(args.prior_option).get("path")
    return [str(p) for p in (args.priors, path) if p and isinstance(p, str)]


def add_localizer_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("localizer")
    g.add_argument("--top-p", type=int, default=50, metavar="N",
                   help="references retrieved before fusion (default 50)")
    g.add_argument("--fusion", choices=FUSION_MODES, default="posterior",
                   help="posterior (default): visual + prior likelihood over the prior's "
                        "confidence region, calibrated radii; paper: nearest submap + re-rank "
                        "by distance to the prior (docs/fusion.md)")
    g.add_argument("--no-submap", action="store_true",
                   help="search the whole map even with a prior (ablation)")
    g.add_argument("--no-rerank", action="store_true",
                   help="ignore the prior when ranking candidates (ablation; posterior: no "
                        "prior term, paper: no re-rank)")
    g.add_argument("--n-submaps", type=int, default=1, metavar="N",
                   help="paper fusion: search the N submaps nearest to the prior (default 1)")


def localizer_config(args: argparse.Namespace) -> LocalizerConfig:
    return LocalizerConfig(top_p=args.top_p, fusion=args.fusion,
                           use_submaps=not args.no_submap, rerank=not args.no_rerank,
                           n_submaps=args.n_submaps)


def add_descriptor_option_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--descriptor-option", metavar="KEY=VALUE", action="append", default=[],
                        help="descriptor setting, repeatable (e.g. pca_dim=128, device=cuda)")
    parser.add_argument("--weights", metavar="PATH", default=None,
                        help="checkpoint file of a deep descriptor (default: torch hub cache)")


def descriptor_options(args: argparse.Namespace) -> dict:
    opts = parse_kv(args.descriptor_option)
    if args.weights:
        opts["weights"] = args.weights
    return opts


def add_verification_args(parser: argparse.ArgumentParser) -> None:
    """Verification and status rule (docs/verification.md): localize."""
    g = parser.add_argument_group("verification and status (docs/verification.md)")
    g.add_argument("--verify-top-k", type=int, default=20, metavar="K",
                   help="candidates verified with local features + geometry (default 20; 0: "
                        "off, every answer unverified and no_fix)")
    g.add_argument("--verify-threads", type=int, default=0, metavar="N",
                   help="threads sharing a query's candidates (default 0: the usable cores, at "
                        "most 4; the answers do not depend on it)")
    g.add_argument("--reference-images", metavar="DIR", default="",
                   help="reference images, for maps that store no local features (maps built "
                        "from descriptors): verified from these images")
    g.add_argument("--verify-preset", metavar="PRESET", default="",
                   help="the verification preset the answers must use (default: the map's "
                        "own); another than the map's is refused, naming both")
    g.add_argument("--verification-required", action="store_true",
                   help="exit 2 when the map has no usable local features (default: warn, "
                        "answers unverified)")
    g.add_argument("--fix-min-p-correct", type=float, default=0.99, metavar="P",
                   help="status 'fix' needs p_correct >= P (default 0.99)")
    g.add_argument("--fix-max-sigma-m", type=float, default=50.0, metavar="M",
                   help="... and a per-axis sigma <= M metres (default 50)")
    g.add_argument("--fix-alert-limit-m", type=float, default=50.0, metavar="M",
                   help="... and a protection level (integrity risk 1e-3) below M metres "
                        "(default 50)")
    g.add_argument("--trust-prior-for-fix", action="store_true",
                   help="prior_resolved answers (decisive only because the prior removed far "
                        "look-alikes) may be fixes")
    g.add_argument("--trust-operator-prior", action="store_true",
                   help="... only for priors with their own sigma_km (--prior fixed)")
    g.add_argument("--feature-option", metavar="KEY=VALUE", action="append", default=[],
                   help="local feature setting not stored in the map, repeatable (e.g. "
                        "weights=PATH for a disk_lightglue map)")
    g.add_argument("--matcher-option", metavar="KEY=VALUE", action="append", default=[],
                   help="matcher setting, repeatable (e.g. weights=PATH for LightGlue)")


def verification_config(args: argparse.Namespace) -> VerificationConfig:
    return VerificationConfig(args.verify_top_k, args.verification_required,
                              args.reference_images, threads=args.verify_threads,
                              feature_options=parse_kv(args.feature_option),
                              matcher_options=parse_kv(args.matcher_option),
                              preset=getattr(args, "verify_preset", ""))


def status_policy(args: argparse.Namespace) -> StatusPolicy:
    return StatusPolicy(args.fix_min_p_correct, args.fix_max_sigma_m, args.trust_prior_for_fix,
                        args.trust_operator_prior,
                        fix_alert_limit_m=getattr(args, "fix_alert_limit_m", 50.0))


def add_local_feature_args(parser: argparse.ArgumentParser) -> None:
    """build-map: which local features the map stores for verification."""
    from vlm_vpr_ros.localization.verification.presets import PRESETS

    parser.add_argument("--local-features", metavar="PRESET", default=None,
                        choices=[*PRESETS, "none"],
                        help="local features stored for verification: "
                             f"{', '.join(PRESETS)} or none (default: sift from images, none "
                             "with --descriptors; docs/verification.md)")
    parser.add_argument("--feature-option", metavar="KEY=VALUE", action="append", default=[],
                        help="local feature setting, repeatable (e.g. weights=PATH for disk)")
    parser.add_argument("--matcher-option", metavar="KEY=VALUE", action="append", default=[],
                        help="matcher setting for the build's calibration, repeatable (e.g. "
                             "weights=PATH for LightGlue)")
    parser.add_argument("--calibration-conditions", metavar="LIST", default=None,
                        help="query conditions of the verification calibration, comma-separated "
                             "(full, fit<W>x<H>, jpeg<Q>_<W>x<H>; default full,fit640x480,"
                             "fit480x360,jpeg40_640x480; docs/verification.md)")


def local_feature_options(args: argparse.Namespace) -> dict:
    """build-map's ``local_features``, ``feature_options`` and ``matcher_options``."""
    return {"local_features": args.local_features
            or ("none" if getattr(args, "descriptors", None) else "sift"),
            "feature_options": parse_kv(args.feature_option),
            "matcher_options": parse_kv(args.matcher_option)}
