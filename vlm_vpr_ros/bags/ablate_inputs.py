"""Query descriptors, ground truth and priors for ``vlm-vpr ablate``, from files or a bag.

Each query is described once and asked for its prior once; the ablation then re-runs only the
(cheap) retrieval for every configuration.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from vlm_vpr_ros.errors import ConfigError, DataError, ImageDecodeError
from vlm_vpr_ros.priors.provider import PriorProvider, PriorQuery, PriorResult

log = logging.getLogger(__name__)


def _collect(items: Iterator[tuple[str, np.ndarray, bytes | None, tuple[float, float]]],
             pipe: Any, provider: PriorProvider, timeout_s: float, total: int | None):
    from tqdm import tqdm

    desc, truth, priors = [], [], []
    for key, rgb, encoded, gt in tqdm(items, total=total, desc="describe+prior", unit="query",
                                      disable=None, leave=False):
        priors.append(provider.get(PriorQuery(image=rgb, encoded=encoded, key=key), timeout_s))
        desc.append(pipe.describe(rgb))
        truth.append(gt)
    if not desc:
        raise DataError("no usable query for the ablation")
    return np.stack(desc).astype(np.float32), np.asarray(truth, dtype=np.float64), priors


def from_files(pipe: Any, provider: PriorProvider, images_dir: str, queries_csv: str,
               timeout_s: float = 60.0) -> tuple[np.ndarray, np.ndarray, list[PriorResult]]:
    from vlm_vpr_ros.files.images import load_image
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv

    rows = read_coords_csv(queries_csv)

    def items():
        for f, lat, lon in rows:
            path = Path(images_dir) / f
            try:
                yield f, load_image(path), path.read_bytes(), (lat, lon)
            except (OSError, ImageDecodeError) as exc:
                log.warning("ablation: skipping query %s: %s", f, exc)

    return _collect(items(), pipe, provider, timeout_s, len(rows))


def from_bag(pipe: Any, provider: PriorProvider, bag_path: str, image_topic: str | None,
             gt_topic: str | None, max_gap_s: float, max_frames: int | None,
             timeout_s: float = 60.0) -> tuple[np.ndarray, np.ndarray, list[PriorResult]]:
    from vlm_vpr_ros.bags.evaluate import _pair
    from vlm_vpr_ros.bags.frames import iter_frames, read_ground_truth
    from vlm_vpr_ros.bags.messages import IMAGE_TYPES, NAVSATFIX
    from vlm_vpr_ros.bags.reader import open_bag

    bag = open_bag(bag_path)
    img = bag.find_topic(IMAGE_TYPES, image_topic, "camera images")
    gt = read_ground_truth(bag, bag.find_topic((NAVSATFIX,), gt_topic, "ground truth").name)

    def items():
        for fr in iter_frames(bag, img.name, max_frames):
            gi, _ = _pair(gt, fr.stamp_ns, max_gap_s)
            if fr.rgb is None or gi is None:
                log.warning("ablation: skipping frame %d (%s)", fr.index,
                            fr.error or "no ground truth close in time")
                continue
            yield fr.key, fr.rgb, fr.encoded, (gt.lat[gi], gt.lon[gi])

    return _collect(items(), pipe, provider, timeout_s, img.count)


def ablation_inputs(args: argparse.Namespace, pipe: Any, provider: PriorProvider):
    """Dispatch on the ``ablate`` arguments: ``--bag`` or ``--images`` + ``--queries``."""
    if args.bag:
        return from_bag(pipe, provider, args.bag, args.image_topic, args.gt_topic,
                        args.max_gt_gap, args.max_frames, args.prior_timeout)
    if not (args.images and args.queries):
        raise ConfigError("ablate needs --bag BAG, or --images DIR with --queries CSV")
    return from_files(pipe, provider, args.images, args.queries, args.prior_timeout)
