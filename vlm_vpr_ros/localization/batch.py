"""Localizing a list of image files (``vlm-vpr localize``, the demo, ablations).

Prior requests run ahead of the descriptor work in a bounded window, so a slow VLM overlaps with
retrieval without unbounded memory."""

from __future__ import annotations

import collections
import itertools
import logging
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence, TypeVar

import numpy as np

from vlm_vpr_ros.errors import ImageDecodeError, VlmVprError
from vlm_vpr_ros.files.csvio import write_csv_atomic
from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
from vlm_vpr_ros.priors.provider import PriorProvider, PriorQuery, PriorResult, wait_prior
from vlm_vpr_ros.redact import redact
from vlm_vpr_ros.types import Hypothesis

log = logging.getLogger(__name__)
T = TypeVar("T")
R = TypeVar("R")

RESULT_FIELDS = ["file", "lat", "lon", "prior_lat", "prior_lon", "prior_source", "prior_reason",
                 "prior_parse", "submap", "ref_id", "uncertainty_m", "radius95_m", "confidence",
                 "fusion", "n_candidates", "flags", "status", "p_correct", "inliers",
                 "inlier_ratio", "protection_m", "descriptor_ms", "retrieval_ms", "rerank_ms",
                 "verify_ms", "prior_latency_s", "top_ids", "top_positions"]
#: called with (file, image, hypothesis) after each localized query (``--save-matches``)
OnResult = Callable[[str, np.ndarray, Hypothesis], None]

#: columns added after results files were first written: empty in older files (resume)
ADDED_FIELDS = ("prior_parse", "status", "p_correct", "inliers", "inlier_ratio", "verify_ms",
                "top_ids", "top_positions", "protection_m")


def started_ahead(items: Iterable[T], start: Callable[[T], R],
                  window: int = 4) -> Iterator[tuple[T, R]]:
    """``(item, start(item))`` in order, with up to ``window`` items started ahead of the one
    handed out: the prior requests of the next queries run while it is localized."""
    it = iter(items)
    pending = collections.deque((x, start(x)) for x in itertools.islice(it, max(1, window)))
    while pending:
        item, handle = pending.popleft()
        for nxt in itertools.islice(it, 1):
            pending.append((nxt, start(nxt)))
        yield item, handle


def localize_files(pipeline: LocalizationPipeline, provider: PriorProvider,
                   images_dir: str | Path, files: Sequence[str], prior_timeout_s: float = 60.0,
                   window: int = 4, on_result: OnResult | None = None) -> Iterator[dict]:
    """Yield one result row per file, in order; unreadable images give a flagged empty row.
    The query's local features (verification) are computed while its prior is pending."""
    images_dir = Path(images_dir)

    def start(f: str) -> tuple[np.ndarray | None, Any, str]:
        try:
            path = images_dir / f
            data = path.read_bytes()
            image = load_image(path)
        except (OSError, ImageDecodeError) as exc:
            return None, None, redact(exc)
        return image, provider.request(PriorQuery(image=image, encoded=data, key=f)), ""

    for f, (image, fut, err) in started_ahead(files, start, window):
        if image is None:
            log.warning("query %s: %s", f, err)
            yield {"file": f, "flags": "image_error", "prior_reason": err}
            continue
        try:
            t0 = time.perf_counter()
            query = pipeline.describe_query(image)
            t_desc = (time.perf_counter() - t0) * 1e3
            prior = wait_prior(fut, provider.name, prior_timeout_s)
            hyp = pipeline.localize_descriptor(query.desc, prior, query.local)
            if on_result is not None:
                on_result(f, image, hyp)
        except VlmVprError as exc:
            log.warning("query %s failed: %s", f, exc)
            yield {"file": f, "flags": "error", "prior_reason": redact(exc)}
            continue
        except Exception as exc:  # noqa: BLE001 - one failing query must not lose the run
            log.warning("query %s failed: internal error %s: %s", f, type(exc).__name__, exc)
            yield {"file": f, "flags": "error",
                   "prior_reason": redact(f"internal error: {type(exc).__name__}: {exc}")}
            continue
        yield result_row(f, hyp, prior, t_desc)


def result_row(file: str, hyp: Hypothesis, prior: PriorResult, descriptor_ms: float) -> dict:
    """One results-CSV row (columns of :data:`RESULT_FIELDS`) for a localized query."""
    row = {"file": file, **hyp.as_row(), "prior_latency_s": f"{prior.latency_s:.3f}"}
    row.update({k: f"{v:.2f}" for k, v in hyp.timings_ms.items()})
    row["descriptor_ms"] = f"{descriptor_ms:.2f}"
    return row


# -- streamed results (localize --out, --resume) -----------------------------------------------
def is_results_csv(path: Path) -> bool:
    """Whether ``path`` is a results CSV written by ``vlm-vpr localize`` (safe to replace)."""
    import csv

    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            header = next(csv.reader(fh), [])
    except (OSError, UnicodeDecodeError, csv.Error):
        return False
    return {"file", "lat", "lon", "flags", "submap"} <= set(header)


def read_done_rows(path: Path) -> list[dict]:
    """Finished rows of a (possibly interrupted) results CSV: a last line cut short by a crash
    or a full disk is dropped, and so are rows flagged ``error`` (retried on resume)."""
    import csv
    import io

    text = path.read_text(encoding="utf-8-sig", errors="replace")
    if text and not text.endswith("\n"):
        text = text[:text.rfind("\n") + 1]
    rows = []
    for row in csv.DictReader(io.StringIO(text, newline="")):
        for k in ADDED_FIELDS:  # a file written before the column existed
            row.setdefault(k, "")
        if any(row.get(k) is None for k in RESULT_FIELDS) or not row.get("file"):
            continue
        if "error" in (row.get("flags") or "").split("|"):
            continue
        rows.append({k: row[k] for k in RESULT_FIELDS})
    return rows


class ResultsStream:
    """Rows appended to ``OUT.partial`` one by one (flushed), renamed to ``OUT`` when done."""

    def __init__(self, out: Path, done: list[dict]) -> None:
        import csv

        self.out, self.partial = out, out.with_name(out.name + ".partial")
        write_csv_atomic(self.partial, RESULT_FIELDS, done)
        self._fh = self.partial.open("a", newline="", encoding="utf-8")
        self._w = csv.DictWriter(self._fh, fieldnames=RESULT_FIELDS, extrasaction="ignore")
        self.rows = list(done)

    def write(self, row: dict) -> None:
        self._w.writerow(row)
        self._fh.flush()
        self.rows.append(row)

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()

    def finish(self, order: Sequence[str]) -> None:
        """Write ``OUT`` in query order atomically, then drop the partial file."""
        self.close()
        rank = {f: i for i, f in enumerate(order)}
        rows = sorted(self.rows, key=lambda r: rank.get(r.get("file"), len(rank)))
        write_csv_atomic(self.out, RESULT_FIELDS, rows)
        self.partial.unlink(missing_ok=True)
