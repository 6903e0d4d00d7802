"""``vlm-vpr localize --save-matches DIR``: per query, one image of the query beside its top
verified candidates with the inlier matches drawn — the view users of VPR tools look at to see
why an answer is right or wrong.

Each row shows the query (left) and one candidate (right), the rank, reference id, inlier count
and, with ground truth, the candidate's distance to the truth; its match lines are green when
the candidate is within the place radius of the truth, red when not (blue without ground
truth). ``only_wrong``: only queries whose answer is more than the place radius off.
Reference images come from the verifier's images folder (``--reference-images`` or the map's own
``images/``); a reference that cannot be read is drawn as a grey panel with its id.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.errors import ConfigError, ImageDecodeError
from vlm_vpr_ros.files.atomic import atomic_write_bytes
from vlm_vpr_ros.files.images import encode_jpeg, load_image
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.types import Hypothesis, LocalFeatures

log = logging.getLogger(__name__)
ROW_HEIGHT = 360
GREEN, RED, BLUE, GREY = (40, 200, 60), (230, 40, 40), (60, 120, 255), (90, 90, 90)


def _fit(image: np.ndarray, height: int) -> tuple[np.ndarray, float]:
    import cv2

    s = height / image.shape[0]
    return cv2.resize(image, (max(1, round(image.shape[1] * s)), height),
                      interpolation=cv2.INTER_AREA), s


def _frame_scale(image: np.ndarray, feats: LocalFeatures) -> float:
    """Original pixels per extraction-frame pixel of ``feats`` extracted from ``image``."""
    w, h = feats.size
    return max(image.shape[:2]) / max(w, h, 1)


def draw_pair(query: np.ndarray, qf: LocalFeatures, ref: np.ndarray | None,
              rf: LocalFeatures | None, matches: np.ndarray, color: tuple[int, int, int],
              title: str) -> np.ndarray:
    """One row: query | reference, inlier matches as lines, ``title`` on top."""
    import cv2

    left, sl = _fit(query, ROW_HEIGHT)
    if ref is None:
        right = np.full((ROW_HEIGHT, ROW_HEIGHT, 3), 60, np.uint8)
        sr = 0.0
    else:
        right, sr = _fit(ref, ROW_HEIGHT)
    canvas = np.concatenate([left, right], axis=1)
    if ref is not None and rf is not None and len(matches):
        a = qf.keypoints[matches[:, 0]] * _frame_scale(query, qf) * sl
        b = rf.keypoints[matches[:, 1]] * _frame_scale(ref, rf) * sr
        b[:, 0] += left.shape[1]
        for (x0, y0), (x1, y1) in zip(a, b):
            cv2.line(canvas, (int(x0), int(y0)), (int(x1), int(y1)), color, 1, cv2.LINE_AA)
            cv2.circle(canvas, (int(x0), int(y0)), 2, color, -1)
            cv2.circle(canvas, (int(x1), int(y1)), 2, color, -1)
    band = np.full((28, canvas.shape[1], 3), 255, np.uint8)
    cv2.putText(band, title[:160], (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1,
                cv2.LINE_AA)
    return np.concatenate([band, canvas], axis=0)


def sheet_name(file: str) -> str:
    """The picture name of query ``file`` (safe characters, ``.jpg``)."""
    return (re.sub(r"[^A-Za-z0-9._-]+", "_", file).strip("_")[-150:] or "query") + ".jpg"


def unique_name(name: str, taken: set[str]) -> str:
    """``name``, or ``name-2.jpg``, ``-3`` ...: two queries never share one picture."""
    k, out = 1, name
    while out in taken:
        k += 1
        out = f"{name[:-4]}-{k}.jpg"
    return out


def sheet_names(files: list[str]) -> dict[str, str]:
    """The picture name of each query of a run (as :class:`MatchWriter` assigns them)."""
    names: dict[str, str] = {}
    taken: set[str] = set()
    for f in files:
        if f not in names:
            names[f] = unique_name(sheet_name(f), taken)
            taken.add(names[f])
    return names


class MatchWriter:
    """The ``on_result`` callback of :func:`vlm_vpr_ros.localization.batch.localize_files`."""

    def __init__(self, out_dir: str | Path, pipeline: Any,
                 ground_truth: Mapping[str, tuple[float, float]] | None = None,
                 only_wrong: bool = False, rows: int = 3, place_radius_m: float = 25.0) -> None:
        if only_wrong and not ground_truth:
            raise ConfigError("--only-wrong needs --ground-truth (which answers are wrong)")
        self.out = Path(out_dir)
        self.pipeline, self.gt, self.only_wrong = pipeline, dict(ground_truth or {}), only_wrong
        self.rows, self.radius_m = rows, place_radius_m
        self.written = 0
        self._names: dict[str, str] = {}  # query file -> picture name (unique in this run)
        self._taken: set[str] = set()

    def _name(self, file: str) -> str:
        if file not in self._names:
            self._names[file] = unique_name(sheet_name(file), self._taken)
            self._taken.add(self._names[file])
        return self._names[file]

    def _truth(self, file: str) -> tuple[float, float] | None:
        import os

        return self.gt.get(file) or self.gt.get(os.path.basename(file))

    def __call__(self, file: str, image: np.ndarray, hyp: Hypothesis) -> None:
        v = self.pipeline.verifier
        truth = self._truth(file)
        err = (float(haversine_km(truth[0], truth[1], hyp.lat, hyp.lon)) * 1000.0
               if truth is not None and math.isfinite(hyp.lat) else math.nan)
        if self.only_wrong and not err > self.radius_m:
            return
        if v is None or not v.enabled or not hyp.matches:
            log.info("query %s: unverified, nothing to draw", file)
            return
        qf = v.query_features(image)
        top = hyp.candidates[:self.rows]
        refs = v.reference_features(top)
        panels = []
        for rank, (c, rf, m) in enumerate(zip(top, refs, hyp.matches), 1):
            d = (float(haversine_km(truth[0], truth[1], c.lat, c.lon)) * 1000.0
                 if truth is not None else math.nan)
            color = BLUE if math.isnan(d) else (GREEN if d <= self.radius_m else RED)
            ref_img = self._reference(c.ref_id)
            title = (f"#{rank} {c.ref_id}  inliers {max(c.inliers, 0)}"
                     + ("" if math.isnan(d) else f"  {d:.0f} m from truth"))
            panels.append(draw_pair(image, qf, ref_img, rf, m, color, title))
        width = max(p.shape[1] for p in panels)
        panels = [np.pad(p, ((0, 0), (0, width - p.shape[1]), (0, 0)), constant_values=255)
                  for p in panels]
        head = (f"{file}: {hyp.status} p_correct {hyp.p_correct:.3f} ratio "
                f"{hyp.inlier_ratio:.2f}" + ("" if math.isnan(err) else f", error {err:.0f} m"))
        sheet = np.concatenate(panels, axis=0)
        import cv2

        band = np.full((30, width, 3), 255, np.uint8)
        cv2.putText(band, head[:170], (6, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1,
                    cv2.LINE_AA)
        name = self._name(file)
        atomic_write_bytes(self.out / name,
                           encode_jpeg(np.concatenate([band, sheet], axis=0), 85))
        self.written += 1

    def _reference(self, ref_id: str) -> np.ndarray | None:
        root = self.pipeline.verifier.images_root
        if root is None:
            return None
        try:
            return load_image(root / ref_id)
        except (ImageDecodeError, OSError):
            return None
