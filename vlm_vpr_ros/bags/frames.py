"""Camera frames and GPS ground truth read from a bag (used by evaluate-bag and ablate)."""

from __future__ import annotations

import csv
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from vlm_vpr_ros.bags.messages import COMPRESSED, stamp_ns
from vlm_vpr_ros.bags.reader import BagReader, RawMessage, deserialize
from vlm_vpr_ros.errors import BagError, ImageDecodeError

log = logging.getLogger(__name__)
#: ground-truth fixes whose own covariance says a horizontal sigma above this (m) are not
#: ground truth: left out of the scoring, counted in one warning (docs/bags.md)
MAX_GT_SIGMA_M = 100.0


@dataclass
class Frame:
    index: int
    stamp_ns: int  # header stamp (log time when the header stamp is zero)
    key: str  # lookup key for recorded priors: source file name (frames.csv) or "sec.nanosec"
    rgb: np.ndarray | None
    encoded: bytes | None = None  # the CompressedImage payload, when there is one
    error: str = ""


@dataclass
class GroundTruth:
    topic: str
    stamps: list[int] = field(default_factory=list)  # sorted, ns
    lat: list[float] = field(default_factory=list)
    lon: list[float] = field(default_factory=list)
    rejected: int = 0  # fixes without a valid position (NO_FIX, NaN, out of range)
    too_uncertain: int = 0  # fixes whose own sigma is above MAX_GT_SIGMA_M


def horizontal_sigma_m(msg) -> float | None:
    """Horizontal standard deviation (m) of a NavSatFix: the larger of the east/north
    variances; None when the covariance is unknown."""
    if msg.position_covariance_type == 0:  # COVARIANCE_TYPE_UNKNOWN
        return None
    cov = msg.position_covariance
    var = max(float(cov[0]), float(cov[4]))
    return math.sqrt(var) if math.isfinite(var) and var >= 0 else math.inf


def _stamp(msg, raw: RawMessage) -> int:
    t = stamp_ns(msg.header)
    return t if t > 0 else raw.log_time_ns


def read_ground_truth(bag: BagReader, topic: str,
                      max_sigma_m: float = MAX_GT_SIGMA_M) -> GroundTruth:
    """Every usable ``NavSatFix`` on ``topic``, sorted by stamp. A fix whose own covariance
    says a horizontal sigma above ``max_sigma_m`` is left out (``too_uncertain``, one warning
    with the count): scoring against a truth of +-1,000 km would be a confident wrong score.
    An unknown covariance (type 0) is kept: most recorded GPS topics do not fill it."""
    from sensor_msgs.msg import NavSatStatus

    items = []
    worst = 0.0
    gt = GroundTruth(topic)
    for raw in bag.messages([topic]):
        try:
            msg = deserialize(raw)
        except BagError as exc:
            log.warning("%s", exc)
            gt.rejected += 1
            continue
        lat, lon = float(msg.latitude), float(msg.longitude)
        ok = (msg.status.status >= NavSatStatus.STATUS_FIX and math.isfinite(lat)
              and math.isfinite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180)
        sigma = horizontal_sigma_m(msg) if ok else None
        if sigma is not None and not sigma <= max_sigma_m:
            gt.too_uncertain += 1
            worst = max(worst, sigma)
        elif ok:
            items.append((_stamp(msg, raw), lat, lon))
        else:
            gt.rejected += 1
    items.sort()
    gt.stamps = [t for t, _, _ in items]
    gt.lat = [a for _, a, _ in items]
    gt.lon = [b for _, _, b in items]
    if gt.rejected:
        log.warning("%s: %d fix(es) without a valid position ignored", topic, gt.rejected)
    if gt.too_uncertain:
        log.warning("%s: %d fix(es) whose own covariance says a sigma above %g m (up to %.3g "
                    "m) are not ground truth: their frames are not scored", topic,
                    gt.too_uncertain, max_sigma_m, worst)
    return gt


def frame_keys(bag: BagReader) -> dict[int, str]:
    """stamp_ns → source file, from the ``frames.csv`` that ``vlm-vpr bag make`` writes."""
    path = Path(bag.path) / "frames.csv" if Path(bag.path).is_dir() else None
    if path is None or not path.is_file():
        return {}
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            return {int(r["stamp_ns"]): r["file"] for r in csv.DictReader(fh)}
    except (OSError, KeyError, ValueError, TypeError) as exc:
        log.warning("ignoring unreadable %s: %s", path, exc)
        return {}


def iter_frames(bag: BagReader, topic: str, max_frames: int | None = None) -> Iterator[Frame]:
    """Decoded frames of an image topic; a frame that cannot be decoded carries ``error``."""
    keys = frame_keys(bag)
    for i, raw in enumerate(bag.messages([topic])):
        if max_frames is not None and i >= max_frames:
            return
        t = raw.log_time_ns
        try:
            msg = deserialize(raw)
            t = _stamp(msg, raw)
            key = keys.get(t) or f"{t // 1_000_000_000}.{t % 1_000_000_000:09d}"
            if raw.type == COMPRESSED:
                encoded = bytes(msg.data)
                yield Frame(i, t, key, decode_compressed(msg), encoded)
            else:
                yield Frame(i, t, key, decode_raw(msg))
        except (BagError, ImageDecodeError) as exc:
            key = keys.get(t) or f"{t // 1_000_000_000}.{t % 1_000_000_000:09d}"
            yield Frame(i, t, key, None, error=str(exc))


def decode_compressed(msg) -> np.ndarray:
    """RGB pixels of a ``sensor_msgs/CompressedImage`` (the node's adapter)."""
    from msg_adapters.image import compressed_to_rgb

    return compressed_to_rgb(msg)


def decode_raw(msg) -> np.ndarray:
    """RGB pixels of a ``sensor_msgs/Image``; unsupported encodings raise ImageDecodeError."""
    from msg_adapters.image import image_to_rgb

    return image_to_rgb(msg)
