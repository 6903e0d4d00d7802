#!/usr/bin/env python3
"""Draw docs/how_it_works.png: the stages of a query and of a map build, named by the code.

Every box is a real function or class of the package (``module:attribute``), resolved by import
before anything is drawn, so a renamed or moved stage fails this script (and its test) instead of
leaving a stale picture. A stage marked optional (a part that is still being built) is drawn only
when its module exists.

    python scripts/draw_stages.py                 # writes docs/how_it_works.png
    python scripts/draw_stages.py --check         # only resolve the names (exit 1 if one is gone)
    python scripts/draw_stages.py --out x.png
"""

from __future__ import annotations

import argparse
import importlib
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Stage:
    target: str  # "package.module:Class.method" or "package.module:function"
    role: str  # what the stage does, in a few words
    optional: bool = False  # drawn only when the module exists (a part being built)

    @property
    def name(self) -> str:
        module, _, attr = self.target.partition(":")
        return f"{module.removeprefix('vlm_vpr_ros.')}\n{attr}"


#: a query's path, from the camera frame to the published fix (the node and the batch tools)
QUERY = (
    Stage("msg_adapters.image:message_to_rgb", "camera frame\n(Image / CompressedImage) → RGB"),
    Stage("vlm_vpr_ros.priors.provider:PriorProvider.request",
          "VLM prior, asynchronous\n(never blocks)"),
    Stage("vlm_vpr_ros.descriptors.global_descriptor:GlobalDescriptor.describe_one",
          "global VPR descriptor"),
    Stage("vlm_vpr_ros.localization.localizer:Localizer.select_submaps",
          "submaps in the prior's\nconfidence region"),
    Stage("vlm_vpr_ros.localization.localizer:Localizer.search",
          "top-p references\n(FAISS, exact merge)"),
    Stage("vlm_vpr_ros.localization.fusion.posterior:fuse",
          "posterior: visual score ×\nVLM error model"),
    Stage("vlm_vpr_ros.localization.localizer:Localizer.calibrated_radii",
          "calibrated 68 / 95 % radii"),
    Stage("vlm_vpr_ros.localization.verification.stage:Verifier.verify",
          "geometric verification of the top K:\nre-rank, inlier ratio, p_correct"),
    Stage("msg_adapters.navsat:navsat_fix",
          "sensor_msgs/NavSatFix\n(fix: verified p_correct + σ)"),
)
#: a map's path, from geotagged images to the folder the node opens
BUILD = (
    Stage("vlm_vpr_ros.mapping.build_images:build_map", "images + CSV (file, lat, lon)"),
    Stage("vlm_vpr_ros.descriptors.global_descriptor:GlobalDescriptor.describe",
          "descriptors\n(fitted first if needed)"),
    Stage("vlm_vpr_ros.maps.partition:make_partition", "submaps: country\nor K-means"),
    Stage("vlm_vpr_ros.maps.indexes:make_index", "one FAISS index\nper submap"),
    Stage("vlm_vpr_ros.maps.store:save_map", "map folder (v2 manifest,\natomic writes)"),
    Stage("vlm_vpr_ros.localization.fusion.calibration:calibrate_references",
          "leave-one-out calibration\n(calibration.json)"),
    Stage("vlm_vpr_ros.mapping.local_features:store_features",
          "local features stored\nper submap"),
    Stage("vlm_vpr_ros.mapping.local_features:calibrate_map",
          "leave-one-out p_correct\n(verification.json)"),
)


def resolve(stage: Stage) -> object | None:
    """The stage's object; None for an optional stage whose module does not exist yet."""
    module, _, attr = stage.target.partition(":")
    try:
        obj = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if stage.optional and exc.name and module.startswith(exc.name):
            return None
        raise
    for part in attr.split("."):
        obj = getattr(obj, part)  # AttributeError: the stage was renamed or moved
    return obj


def present(stages: tuple[Stage, ...]) -> list[Stage]:
    return [s for s in stages if resolve(s) is not None]


def draw(out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyArrowPatch, FancyBboxPatch

    from vlm_vpr_ros.files.atomic import atomic_path

    rows = [("a query (online: the node; offline: localize, evaluate-bag)", present(QUERY),
             "#e8f0fb", "#3b6fd6"),
            ("a map (offline: build-map)", present(BUILD), "#eef7ea", "#1a9641")]
    width = max(len(r[1]) for r in rows)
    fig, ax = plt.subplots(figsize=(2.05 * width, 5.4))
    w, h, gap = 1.75, 1.25, 0.3
    for r, (title, stages, face, edge) in enumerate(rows):
        y = (len(rows) - 1 - r) * 2.4
        ax.text(0, y + h + 0.22, title, fontsize=10, weight="bold", va="bottom")
        for i, stage in enumerate(stages):
            x = i * (w + gap)
            ax.add_patch(FancyBboxPatch((x, y), w, h, fc=face, ec=edge, lw=1.3,
                                        boxstyle="round,pad=0.03,rounding_size=0.08"))
            ax.text(x + w / 2, y + h - 0.1, stage.name, ha="center", va="top", fontsize=6.4,
                    family="monospace")
            ax.text(x + w / 2, y + 0.1, stage.role, ha="center", va="bottom", fontsize=6.8,
                    color="#333333")
            if i:
                ax.add_patch(FancyArrowPatch((x - gap, y + h / 2), (x, y + h / 2),
                                             arrowstyle="-|>", mutation_scale=10, lw=1.1,
                                             color=edge))
    ax.text(0, -0.55, "The build's calibration feeds the query's radii; the map folder is what "
                      "the query path opens. Names are the package's own (scripts/draw_stages.py"
                      " resolves each by import).", fontsize=7.5, color="#555555")
    ax.set_xlim(-0.1, width * (w + gap))
    ax.set_ylim(-0.8, 2.4 * (len(rows) - 1) + h + 0.6)
    ax.axis("off")
    fig.tight_layout()
    with atomic_path(out, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Draw docs/how_it_works.png (the stages of a query "
                                            "and of a map build) from the package's own names.")
    p.add_argument("--out", default=str(REPO / "docs" / "how_it_works.png"), metavar="PNG")
    p.add_argument("--check", action="store_true", help="only check that every stage resolves")
    args = p.parse_args(argv)
    try:
        stages = present(QUERY) + present(BUILD)
    except (ImportError, AttributeError) as exc:
        print(f"draw_stages: a stage no longer exists in the code: {exc}", file=sys.stderr)
        return 1
    if args.check:
        print(f"draw_stages: {len(stages)} stages resolve", file=sys.stderr)
        return 0
    print(f"draw_stages: wrote {draw(Path(args.out))}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
