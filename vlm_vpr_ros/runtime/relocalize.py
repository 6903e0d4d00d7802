"""Relocalization requests of the node's runtime (pure, no ROS).

A request names a *kind* (:class:`RelocalizeKind`): which frame to use and whether to ask the
prior provider. Concurrent requests of one kind share one query (:class:`RelocalizeTicket`);
every caller waits for that shared outcome, bounded by its own wait time. The node offers one
``std_srvs/Trigger`` service per kind (docs/node.md "Services"), because Trigger carries no
fields and a custom service type cannot be generated from the PyPI wheels.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.localization.verification.status import horizontal_sigma, is_precise_fix

FRAME_POLICIES = ("latest", "next")


@dataclass(frozen=True)
class RelocalizeKind:
    """What a relocalize caller asks for.

    ``frame``: ``latest`` uses the newest frame if it was received at most ``max_frame_age_s``
    ago, else the next one; ``next`` uses the first frame received after the request (the
    camera was covered, the robot was just carried somewhere). ``use_prior``: False skips the
    prior provider (global retrieval, flagged ``no_prior``): no VLM call and no VLM latency.
    """

    frame: str = "latest"
    use_prior: bool = True

    def __post_init__(self) -> None:
        if self.frame not in FRAME_POLICIES:
            raise ConfigError(f"unknown relocalize frame policy {self.frame!r}; choices: "
                              f"{', '.join(FRAME_POLICIES)}")

    @property
    def label(self) -> str:
        return f"{self.frame} frame, {'with' if self.use_prior else 'without'} prior"


class RelocalizeTicket:
    """A pending relocalization of one kind; its callers wait for the shared outcome."""

    def __init__(self, kind: RelocalizeKind, after_seq: int) -> None:
        self.kind = kind
        self.after_seq = after_seq  # frames numbered above this arrived after the request
        self.requested = time.monotonic()
        self._done = threading.Event()
        self.outcome: Any = None  # the worker's QueryOutcome

    def accepts(self, frame: Any, now: float, max_age_s: float) -> bool:
        """Whether ``frame`` (the worker's Frame, or None) may answer this request at time
        ``now`` (the runtime's clock)."""
        if frame is None:
            return False
        if self.kind.frame == "next":
            return frame.seq > self.after_seq
        return now - frame.received <= max_age_s

    def finish(self, outcome: Any) -> None:
        self.outcome = outcome
        self._done.set()

    def wait(self, timeout_s: float) -> Any:
        self._done.wait(max(0.0, timeout_s))
        return self.outcome


def outcome_summary(outcome: Any, waited_s: float,
                    fix_topic: str = "fix") -> tuple[bool, str]:
    """(success, human-readable sentence) answering a relocalize request (``outcome``: the
    worker's QueryOutcome, None when none came in time). ``success`` means the robot may act
    on the answer: a STATUS_FIX that passed the status rule (the answers that also go out on
    ``pose``); a NO_FIX or a ``fallback_status: fix`` answer is reported, with success false."""
    if outcome is None:
        return False, (f"relocalization scheduled, no result within {waited_s:.1f} s (waiting "
                       f"for a frame or for the prior); the fix will be published on "
                       f"{fix_topic}")
    frame = outcome.frame
    if outcome.hypothesis is None:
        return False, f"relocalization on frame {frame.key} gave no fix: {outcome.error}"
    h = outcome.hypothesis
    pr = h.prior_result
    if h.prior is not None:
        prior = f"prior {h.prior.source} ({h.prior.lat:.4f}, {h.prior.lon:.4f})"
    else:
        prior = f"no prior ({pr.reason if pr else 'not asked'}): global retrieval"
    flag = f" FLAGGED [{'|'.join(h.flags)}]" if h.flagged else ""
    # the status and sigma of the published fix (docs/verification.md)
    status = ((f"STATUS_FIX ({h.status_reason})" if h.status_reason else "STATUS_FIX")
              if h.status == "fix" else f"NO_FIX ({h.status_reason or 'unverified'})")
    p = "" if math.isnan(h.p_correct) else f"p_correct {h.p_correct:.3f}, "
    if math.isfinite(h.protection_m):  # integrity: the error bound at risk 1e-3
        p = f"protection {h.protection_m:.0f} m, {p}"
    took = outcome.finished - outcome.started
    what = "relocalized frame" if outcome.trigger == "relocalize" else "fix for frame"
    return is_precise_fix(h), (f"{what} {frame.key}: lat {h.lat:.6f}, lon {h.lon:.6f}, "
                               f"{status}, sigma {horizontal_sigma(h):.0f} m, {p}reference "
                               f"{h.ref_id}, submap {h.submap}, {prior}, "
                               f"{len(h.candidates)} candidates, {took:.2f} s{flag}")
