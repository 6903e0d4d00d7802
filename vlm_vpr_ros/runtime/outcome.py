"""What the query worker takes and gives (pure): a received frame and a query's outcome."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vlm_vpr_ros.types import Hypothesis


@dataclass
class Frame:
    """A received, not yet decoded image message."""

    msg: Any
    stamp_ns: int
    frame_id: str
    received: float = field(default_factory=time.monotonic)
    seq: int = 0  # arrival number (set by QueryRuntime.on_frame)

    @property
    def key(self) -> str:
        """Lookup key handed to the prior provider: the stamp as ``sec.nanosec``."""
        return f"{self.stamp_ns // 1_000_000_000}.{self.stamp_ns % 1_000_000_000:09d}"


@dataclass
class QueryOutcome:
    frame: Frame
    trigger: str  # "continuous" or "relocalize"
    hypothesis: Hypothesis | None = None
    error: str = ""  # why there is no hypothesis
    started: float = 0.0
    finished: float = 0.0
    timings_ms: dict[str, float] = field(default_factory=dict)
    rgb: np.ndarray | None = field(default=None, repr=False)  # kept when keep_images is set
    #: the answer's inlier matches, (n, 4) fractions of the query and reference images
    #: (debug_view.winner_matches; only with keep_images and a verified answer)
    matches: np.ndarray | None = field(default=None, repr=False)
