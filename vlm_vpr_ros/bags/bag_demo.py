"""The bag part of ``vlm-vpr demo``: images → demo bag → offline evaluation with plots."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Sequence

from vlm_vpr_ros.geodesy import THRESHOLDS_KM

log = logging.getLogger(__name__)

#: stamp of the demo bag's first frame (fixed, so repeated demos give identical bags)
DEMO_START_NS = 1_700_000_000_000_000_000


def run_bag_demo(out_dir: str | os.PathLike[str], map_dir: str | os.PathLike[str],
                 images_dir: str | os.PathLike[str], coords_csv: str | os.PathLike[str],
                 priors_csv: str | os.PathLike[str] | None = None,
                 thresholds_km: Sequence[float] = THRESHOLDS_KM) -> dict:
    """Make ``out_dir/demo_bag`` (CompressedImage at 2 Hz + NavSatFix) from ``images_dir``/
    ``coords_csv`` and evaluate it against ``map_dir`` with recorded priors (if given).
    Returns the output paths and the accuracy summary (key ``summary``, at
    ``thresholds_km``, with the frames' ``fixes``)."""
    from vlm_vpr_ros.bags.evaluate import evaluate_bag
    from vlm_vpr_ros.bags.make import make_bag
    from vlm_vpr_ros.bags.reader import open_bag
    from vlm_vpr_ros.evaluation.metrics import summarize
    from vlm_vpr_ros.files.csvio import read_table
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.priors import create_prior_provider

    out = Path(out_dir)
    bag_dir = out / "demo_bag"
    make_bag(images_dir, coords_csv, bag_dir, rate_hz=2.0, compressed=True,
             start_time_ns=DEMO_START_NS, overwrite=True, progress=False)
    provider = create_prior_provider("recorded", {"path": str(priors_csv)}) if priors_csv \
        else create_prior_provider("none")
    pipe = LocalizationPipeline.open(map_dir)
    try:
        res = evaluate_bag(open_bag(bag_dir), pipe, provider, out / "evaluation",
                           progress=False, overwrite=True)
    finally:
        provider.close()
    info = {"bag": str(bag_dir)}
    info.update(res["details"]["outputs"])
    frames = read_table(out / "evaluation" / "frames.csv", ("error_km",), "frames CSV")
    info["summary"] = {**summarize([float(r["error_km"]) if r["error_km"] else None
                                    for r in frames if r["gt_lat"]], thresholds_km),
                       "fixes": res["fixes"]}  # the same frames: evaluate-bag's fix rate
    return info
