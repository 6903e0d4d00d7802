"""Query conditions the verification calibration covers (docs/verification.md section 2).

A robot sends frames of its own camera, not the references as stored: smaller (640×480,
480×360) and JPEG-compressed. The leave-one-out calibration therefore runs its queries under
each of a set of *conditions*, each a degraded copy of the reference image used as the query:

* ``full``: the reference as stored (its stored local features, as before conditions existed);
* ``fit<W>x<H>``: the image fitted inside W×H pixels, aspect kept (never enlarged);
* ``jpeg<Q>_<W>x<H>``: fitted inside W×H, then JPEG-encoded at quality Q and decoded.

The map records the conditions it was calibrated for and the smallest frame among them
(longer side, pixels); a query frame whose longer side is below it is *outside* the calibration
(the node and CLI warn once: the bound of ``p_correct`` was not measured on such frames).
"""

from __future__ import annotations

import logging
import re
import threading
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from vlm_vpr_ros.errors import ConfigError

log = logging.getLogger(__name__)

#: the default mix: full size, two robot camera sizes and a heavily compressed stream
DEFAULT_CONDITIONS = ("full", "fit640x480", "fit480x360", "jpeg40_640x480")
_FIT = re.compile(r"^fit(\d{2,5})x(\d{2,5})$")
_JPEG = re.compile(r"^jpeg(\d{1,3})_(\d{2,5})x(\d{2,5})$")


@dataclass(frozen=True)
class Condition:
    name: str
    box: tuple[int, int] | None = None  # fit inside (width, height); None: as stored
    jpeg_quality: int | None = None

    def apply(self, image: np.ndarray) -> np.ndarray:
        """The degraded copy of ``image`` (HxW or HxWxC uint8)."""
        import cv2

        out = image
        if self.box is not None:
            h, w = image.shape[:2]
            s = min(self.box[0] / w, self.box[1] / h, 1.0)
            if s < 1.0:
                size = (max(1, round(w * s)), max(1, round(h * s)))
                out = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        if self.jpeg_quality is not None:
            rgb = out.ndim == 3 and out.shape[2] == 3
            bgr = cv2.cvtColor(out, cv2.COLOR_RGB2BGR) if rgb else out
            ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            if not ok:
                raise ConfigError(f"condition {self.name}: JPEG encoding failed")
            out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
            out = cv2.cvtColor(out, cv2.COLOR_BGR2RGB) if rgb else out
        return out


def parse_condition(name: str) -> Condition:
    """``full``, ``fit<W>x<H>`` or ``jpeg<Q>_<W>x<H>``; ConfigError naming the choices."""
    n = str(name).strip()
    if n == "full":
        return Condition("full")
    m = _FIT.match(n)
    if m:
        return Condition(n, (int(m[1]), int(m[2])))
    m = _JPEG.match(n)
    if m and 1 <= int(m[1]) <= 100:
        return Condition(n, (int(m[2]), int(m[3])), int(m[1]))
    raise ConfigError(f"calibration condition {name!r} unknown: use full, fit<W>x<H> "
                      "(e.g. fit640x480) or jpeg<Q>_<W>x<H> (e.g. jpeg40_640x480)")


def parse_conditions(names: str | Sequence[str] | None) -> tuple[Condition, ...]:
    """A comma-separated list or a sequence of names (None: :data:`DEFAULT_CONDITIONS`); at
    least one, no repeats."""
    if names is None:
        names = DEFAULT_CONDITIONS
    if isinstance(names, str):
        names = [n for n in names.split(",") if n.strip()]
    conds = tuple(parse_condition(n) for n in names)
    if not conds:
        raise ConfigError("calibration conditions: give at least one (e.g. full)")
    if len({c.name for c in conds}) != len(conds):
        raise ConfigError("calibration conditions: a condition is listed twice")
    return conds


def frame_long_side(shape: Sequence[int]) -> int:
    return int(max(shape[0], shape[1]))


class ConditionWatch:
    """Warns once when query frames are smaller than the calibration covered (module
    docstring). ``min_long_side``: the smallest calibrated frame's longer side (0: unknown, a
    map calibrated before conditions existed: warns once that it is ``uncalibrated_conditions``
    for any frame below full size is not knowable, so it says nothing per frame)."""

    def __init__(self, where: str, min_long_side: int, conditions: Sequence[str]) -> None:
        self.where, self.min_long_side = where, int(min_long_side)
        self.conditions = list(conditions)
        self._warned = False
        self._lock = threading.Lock()

    def outside(self, shape: Sequence[int]) -> bool:
        return self.min_long_side > 0 and frame_long_side(shape) < self.min_long_side

    def check(self, shape: Sequence[int]) -> bool:
        """Whether a frame of ``shape`` is outside the calibrated conditions (warned once)."""
        if not self.outside(shape):
            return False
        with self._lock:
            if not self._warned:
                self._warned = True
                log.warning("%s: query frames of %dx%d are smaller than the verification "
                            "calibration covered (conditions %s, smallest longer side %d px): "
                            "p_correct was not measured on such frames (recalibrate with "
                            "'vlm-vpr calibrate --map MAP --conditions ...')", self.where,
                            shape[1], shape[0], ",".join(self.conditions), self.min_long_side)
        return True
