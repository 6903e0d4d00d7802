"""Debug view of one query (pure: no ROS): what the node matched.

:func:`render` puts the query beside the chosen reference image (both scaled to one height),
with a caption (status, sigma, reference, prior, posterior weight) and, when the caller passes
them, verified matches as lines between the two images. :class:`ReferenceImages` finds the
reference pictures: the map's own ``images/`` folder (teach maps keep them), the folder a
``build-map --images`` map records it was built from, or a folder the user names
(``reference_images_dir``); a map built from images shows a picture only while its bytes are
those the build read (:class:`~vlm_vpr_ros.maps.map_images.SourceImages`). :func:`candidate_rows`
lists the best candidates with their posterior weights and inliers, :func:`answer_row` the
verified answer (status, ``p_correct``, inliers). :func:`winner_matches` takes the inlier matches
of the verified answer out of the query (worker side, cheap: one row of the map's feature
store); :func:`match_pixels` places them on the two pictures. Rendering runs only when
``publish_debug`` is on (the node then asks the runtime to keep the decoded frame and the
matches).
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from pathlib import Path
from typing import Any, Mapping, Sequence

import cv2
import numpy as np

from vlm_vpr_ros.errors import ImageDecodeError, VlmVprError
from vlm_vpr_ros.files.images import decode_image_bytes, encode_jpeg
from vlm_vpr_ros.maps.map_images import SourceImages

log = logging.getLogger(__name__)
PANEL_HEIGHT = 360  # px: both images are scaled to this height
PANEL_MAX_WIDTH = 1280  # px: ... and at most this wide (a 10000x10 strip stays encodable)
#: JPEG's largest side (baseline 16-bit sizes); a larger picture is never handed to the encoder
JPEG_MAX_SIDE = 65500
CAPTION_HEIGHT = 48
MAX_CANDIDATES_LISTED = 10
_FONT = cv2.FONT_HERSHEY_SIMPLEX


class ReferenceImages:
    """Reference pictures by reference id, scaled to the panel height (a small LRU cache)."""

    def __init__(self, folder: str | Path | None, cache_size: int = 16,
                 files: SourceImages | None = None) -> None:
        self.files = files if files is not None else SourceImages(folder)
        self.folder = self.files.folder
        self._cache: OrderedDict[str, tuple[np.ndarray, float] | None] = OrderedDict()
        self._size = cache_size

    @classmethod
    def for_map(cls, map_path: str | Path | None, manifest: Mapping[str, Any],
                override: str = "") -> "ReferenceImages":
        """``override`` when given, else the map's own images folder when it keeps one, else
        the folder the map was built from while it exists; pictures of a map built from images
        are checked against the build's index (:meth:`SourceImages.for_map`)."""
        return cls(None, files=SourceImages.for_map(map_path, manifest, override))

    def load(self, ref_id: str) -> tuple[np.ndarray, float] | None:
        """(RGB thumbnail, thumbnail px per original px), or None when unavailable."""
        if ref_id in self._cache:
            self._cache.move_to_end(ref_id)
            return self._cache[ref_id]
        found = None
        data = self.files.read(ref_id)  # None: missing, outside the folder, changed (WARN)
        if data is not None:
            try:
                found = _scaled(decode_image_bytes(data, f"reference image {ref_id}"))
            except VlmVprError as exc:
                log.debug("reference image %s not available: %s", ref_id, exc)
        self._cache[ref_id] = found
        if len(self._cache) > self._size:
            self._cache.popitem(last=False)
        return found


def _scaled(rgb: np.ndarray, height: int = PANEL_HEIGHT,
            max_width: int = PANEL_MAX_WIDTH) -> tuple[np.ndarray, float]:
    """``rgb`` scaled to ``height`` (at most ``max_width`` wide: then padded to ``height``)
    and the scale (panel px per original px)."""
    s = min(height / max(1, rgb.shape[0]), max_width / max(1, rgb.shape[1]))
    w = max(1, int(round(rgb.shape[1] * s)))
    h = max(1, min(height, int(round(rgb.shape[0] * s))))
    small = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    if h == height:
        return small, s
    out = np.zeros((height, w, 3), np.uint8)
    out[:h] = small
    return out, s


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.5) -> None:
    """``text`` drawn once, white on a dark box (legible on any picture)."""
    (w, h), base = cv2.getTextSize(text, _FONT, scale, 1)
    x, y = org
    x0, y0 = max(0, x - 2), max(0, y - h - 3)
    x1, y1 = min(img.shape[1], x + w + 2), min(img.shape[0], y + base + 2)
    if x1 > x0 and y1 > y0:
        img[y0:y1, x0:x1] = (img[y0:y1, x0:x1] // 4)
    cv2.putText(img, text, org, _FONT, scale, (255, 255, 255), 1, cv2.LINE_AA)


def render(query_rgb: np.ndarray, reference: tuple[np.ndarray, float] | None,
           caption: Sequence[str], ref_label: str = "",
           matches: np.ndarray | None = None) -> np.ndarray:
    """The debug picture (RGB): query | reference, caption below. ``matches``: (n, 4) pixel
    coordinates ``qx, qy, rx, ry`` in the original query and reference images."""
    q, qs = _scaled(query_rgb)
    if reference is not None:
        r, rs = reference
    else:
        r, rs = np.full((PANEL_HEIGHT, q.shape[1], 3), 64, np.uint8), 1.0
        _text(r, "reference image not available", (10, PANEL_HEIGHT // 2))
        _text(r, "(set reference_images_dir)", (10, PANEL_HEIGHT // 2 + 22))
    canvas = np.zeros((PANEL_HEIGHT + CAPTION_HEIGHT, q.shape[1] + r.shape[1], 3), np.uint8)
    canvas[:PANEL_HEIGHT, :q.shape[1]] = q
    canvas[:PANEL_HEIGHT, q.shape[1]:] = r
    _text(canvas, "query", (8, 20))
    _text(canvas, ref_label or "reference", (q.shape[1] + 8, 20))
    if matches is not None and reference is not None and len(matches):
        m = np.asarray(matches, dtype=np.float64)
        pts = np.column_stack([m[:, 0] * qs, m[:, 1] * qs, m[:, 2] * rs + q.shape[1],
                               m[:, 3] * rs]).round().astype(np.int32)
        for qx, qy, rx, ry in pts:
            cv2.line(canvas, (int(qx), int(qy)), (int(rx), int(ry)), (0, 255, 0), 1,
                     cv2.LINE_AA)
    for i, line in enumerate(caption[:2]):
        _text(canvas, line, (8, PANEL_HEIGHT + 18 + 22 * i))
    return canvas


def winner_matches(verifier: Any, query: Any, hyp: Any) -> np.ndarray | None:
    """The verified answer's inlier matches as fractions of each image, (n, 4) float32
    ``qx, qy, rx, ry`` (``query``: the query's LocalFeatures; None when the answer was not
    verified). A keypoint's place in the extraction frame, as a fraction of the frame's width
    and height, is its place in the original image: the frame keeps the aspect ratio."""
    if verifier is None or query is None or not hyp.matches or not hyp.candidates:
        return None
    pairs = hyp.matches[0]  # aligned with hyp.candidates[0], the answer
    ref = verifier.reference_features(hyp.candidates[:1])[0]
    if ref is None or not len(pairs):
        return None
    q = query.keypoints[pairs[:, 0]] / np.maximum(np.asarray(query.size, np.float32), 1.0)
    r = ref.keypoints[pairs[:, 1]] / np.maximum(np.asarray(ref.size, np.float32), 1.0)
    return np.hstack([q, r]).astype(np.float32)


def match_pixels(fractions: np.ndarray | None, query_shape: tuple[int, ...],
                 reference: tuple[np.ndarray, float] | None) -> np.ndarray | None:
    """:func:`winner_matches` in pixels of the original query and reference images (what
    :func:`render` draws); None without matches or without the reference picture."""
    if fractions is None or reference is None or not len(fractions):
        return None
    thumb, s = reference
    size = np.array([query_shape[1], query_shape[0], thumb.shape[1] / s, thumb.shape[0] / s])
    return np.asarray(fractions, np.float64) * size


def jpeg(rgb: np.ndarray, quality: int = 85) -> bytes:
    """JPEG bytes of the picture; ImageDecodeError (one line, no OpenCV message) when JPEG
    cannot hold it."""
    if max(rgb.shape[:2]) > JPEG_MAX_SIDE or min(rgb.shape[:2]) < 1:
        raise ImageDecodeError(f"JPEG encoding failed: a {rgb.shape[1]}x{rgb.shape[0]} "
                               f"picture (JPEG holds at most {JPEG_MAX_SIDE} px a side)")
    return encode_jpeg(rgb, quality)


def _num(v: Any, fmt: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return format(v, fmt)


def candidate_rows(hyp: Any, limit: int = MAX_CANDIDATES_LISTED) -> list[dict[str, str]]:
    """The best candidates of a hypothesis, best first: id, position, descriptor distance,
    posterior weight, distance to the prior, geometric inliers ('' where not computed)."""
    rows = []
    for rank, c in enumerate(hyp.candidates[:limit], 1):
        inliers = getattr(c, "inliers", -1)
        rows.append({"rank": str(rank), "ref_id": c.ref_id, "lat": _num(c.lat, ".7f"),
                     "lon": _num(c.lon, ".7f"), "submap": c.submap,
                     "l2_sq": _num(c.l2_sq, ".4f"), "posterior": _num(c.posterior, ".4f"),
                     "prior_km": _num(c.prior_km, ".1f"),
                     "inliers": str(inliers) if inliers is not None and inliers >= 0 else ""})
    return rows


def answer_row(hyp: Any, status: str, reason: str, sigma_m: float) -> dict[str, str]:
    """The answer of a query for ``~/candidates``: status (and why not a fix), the verified
    evidence (``p_correct``, inliers, inlier ratio) and the published sigma."""
    return {"status": status, "status_reason": reason, "ref_id": hyp.ref_id,
            "p_correct": _num(hyp.p_correct, ".4f"),
            "inliers": str(hyp.inliers) if hyp.inliers >= 0 else "",
            "inlier_ratio": _num(hyp.inlier_ratio, ".2f"), "sigma_m": _num(sigma_m, ".1f"),
            "verification": hyp.verification or "unverified",
            "flags": "|".join(hyp.flags)}


def caption(hyp: Any, status: str, sigma_m: float, error: str = "") -> list[str]:
    """Two caption lines for a query's outcome (``hyp`` None: the error)."""
    if hyp is None:
        return [f"no fix: {error}"[:110], ""]
    top = hyp.candidates[0] if hyp.candidates else None
    weight = f", posterior {top.posterior:.2f}" if top is not None and top.posterior else ""
    prior = (f"prior {hyp.prior.source} ({hyp.prior.lat:.4f}, {hyp.prior.lon:.4f})"
             if hyp.prior is not None else "no prior: global retrieval")
    flags = f" FLAGGED [{'|'.join(hyp.flags)}]" if hyp.flagged else ""
    first = f"{status} sigma {sigma_m:.0f} m  ref {hyp.ref_id} (submap {hyp.submap}){weight}"
    verified = (f"p_correct {_num(hyp.p_correct, '.3f') or '-'}, {hyp.inliers} inliers; "
                if hyp.inliers >= 0 else "")
    return [first[:110], f"{verified}{prior}, {len(hyp.candidates)} candidates{flags}"[:110]]
