"""Localizing a list of image files (``vlm-vpr localize``, the demo, ablations).

Prior requests run ahead of the descriptor work in a bounded window, so a slow VLM overlaps with
retrieval without unbounded memory."""

from __future__ import annotations

import collections
import logging
import time
from pathlib import Path
from typing import Iterator, Sequence

from vlm_vpr_ros.errors import ImageDecodeError, VlmVprError
from vlm_vpr_ros.imageio import load_image
from vlm_vpr_ros.pipeline import LocalizationPipeline
from vlm_vpr_ros.priors.base import PriorProvider, PriorQuery, wait_prior

log = logging.getLogger(__name__)

RESULT_FIELDS = ["file", "lat", "lon", "prior_lat", "prior_lon", "prior_source", "prior_reason",
                 "submap", "ref_id", "uncertainty_m", "n_candidates", "flags",
                 "descriptor_ms", "retrieval_ms", "rerank_ms", "prior_latency_s"]


def localize_files(pipeline: LocalizationPipeline, provider: PriorProvider,
                   images_dir: str | Path, files: Sequence[str], prior_timeout_s: float = 60.0,
                   window: int = 4) -> Iterator[dict]:
    """Yield one result row per file, in order; unreadable images give a flagged empty row."""
    images_dir = Path(images_dir)
    pending: collections.deque = collections.deque()
    it = iter(files)

    def submit() -> bool:
        f = next(it, None)
        if f is None:
            return False
        try:
            path = images_dir / f
            data = path.read_bytes()
            image = load_image(path)
        except (OSError, ImageDecodeError) as exc:
            pending.append((f, None, None, str(exc)))
            return True
        fut = provider.request(PriorQuery(image=image, encoded=data, key=f))
        pending.append((f, image, fut, ""))
        return True

    for _ in range(max(1, window)):
        if not submit():
            break
    while pending:
        f, image, fut, err = pending.popleft()
        submit()
        if image is None:
            log.warning("query %s: %s", f, err)
            yield {"file": f, "flags": "image_error", "prior_reason": err}
            continue
        try:
            t0 = time.perf_counter()
            desc = pipeline.describe(image)
            t_desc = (time.perf_counter() - t0) * 1e3
            prior = wait_prior(fut, provider.name, prior_timeout_s)
            hyp = pipeline.localize_descriptor(desc, prior)
        except VlmVprError as exc:
            log.warning("query %s failed: %s", f, exc)
            yield {"file": f, "flags": "error", "prior_reason": str(exc)}
            continue
        row = {"file": f, **hyp.as_row(), "prior_latency_s": f"{prior.latency_s:.3f}"}
        row.update({k: f"{v:.2f}" for k, v in hyp.timings_ms.items()})
        row["descriptor_ms"] = f"{t_desc:.2f}"
        yield row
