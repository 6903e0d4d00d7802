"""Localizing precomputed query descriptors (``vlm-vpr localize --query-descriptors``).

No descriptor is computed, so neither the model nor its weights are loaded: the map is opened,
rows of ``Q.npy`` (aligned with the queries CSV) go straight to the localizer. Priors come from
the usual providers; a provider that needs pixels (a VLM) gets the image when ``--images`` is
given. A NaN/inf or all-zero query row gives a flagged empty result row.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from vlm_vpr_ros.localization.batch import result_row, started_ahead
from vlm_vpr_ros.errors import DataError, ImageDecodeError, VlmVprError
from vlm_vpr_ros.localization.localizer import Localizer
from vlm_vpr_ros.localization.pipeline import verify_and_stamp
from vlm_vpr_ros.localization.verification.status import StatusPolicy
from vlm_vpr_ros.maps.sources import open_npy
from vlm_vpr_ros.priors.provider import PriorProvider, PriorQuery, wait_prior

log = logging.getLogger(__name__)


def open_query_descriptors(path: str | Path, n_queries: int, dim: int) -> np.ndarray:
    """Memory-mapped (n, dim) query descriptors; DataError unless they match the CSV and map."""
    arr = open_npy(Path(path))
    if arr.shape[0] != n_queries:
        raise DataError(f"{path}: {arr.shape[0]} query descriptors but the queries CSV has "
                        f"{n_queries} rows (rows must align)")
    if arr.shape[1] != dim:
        raise DataError(f"{path}: query descriptors are {arr.shape[1]}-D, the map is {dim}-D")
    return arr


def localize_descriptors(localizer: Localizer, provider: PriorProvider, files: Sequence[str],
                         descs: np.ndarray, images_dir: str | Path | None = None,
                         prior_timeout_s: float = 60.0, window: int = 4,
                         verifier: Any = None, policy: Any = None,
                         local: Sequence[Any] | None = None) -> Iterator[dict]:
    """Yield one result row per query (columns of batch.RESULT_FIELDS), in order. With a
    ``verifier``, answers are verified with the query's local features: ``local`` (rows
    aligned with ``descs``, e.g. from the descriptor's own SIFT pass,
    :meth:`LocalizationPipeline.describe_query`) or extracted from the image in
    ``images_dir``; without either they are flagged ``unverified``. Statuses follow
    ``policy`` (default StatusPolicy)."""
    policy = policy or StatusPolicy()

    def start(item: tuple[int, str]) -> Any:
        f = item[1]
        query = PriorQuery(key=f)
        if images_dir is not None:
            from vlm_vpr_ros.files.images import load_image

            try:
                path = Path(images_dir) / f
                query = PriorQuery(image=load_image(path), encoded=path.read_bytes(), key=f)
            except (OSError, ImageDecodeError) as exc:
                log.warning("query %s: image for the prior unreadable (%s)", f, exc)
        return query.image, provider.request(query)

    for (i, f), (image, fut) in started_ahead(enumerate(files), start, window):
        q = np.asarray(descs[i], dtype=np.float32)
        if not np.all(np.isfinite(q)) or not q.any():
            yield {"file": f, "flags": "bad_descriptor",
                   "prior_reason": "query descriptor is NaN/inf or zero"}
            continue
        try:
            prior = wait_prior(fut, provider.name, prior_timeout_s)
            hyp = localizer.localize(q, prior)
            feats = local[i] if local is not None else None
            if feats is None and verifier is not None and verifier.enabled \
                    and image is not None:
                feats = verifier.query_features(image)
            verify_and_stamp(hyp, feats, verifier, localizer, policy)
        except VlmVprError as exc:
            log.warning("query %s failed: %s", f, exc)
            yield {"file": f, "flags": "error", "prior_reason": str(exc)}
            continue
        yield result_row(f, hyp, prior, 0.0)  # no descriptor computed
