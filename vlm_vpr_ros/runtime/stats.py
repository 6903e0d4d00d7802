"""Counters and last-query facts of the node's runtime, summarized for /diagnostics."""

from __future__ import annotations

import threading
import time
from typing import Any

from vlm_vpr_ros.localization.verification.status import horizontal_sigma
from vlm_vpr_ros.types import Hypothesis

#: a decode error this recent keeps the diagnostics at WARN
RECENT_ERROR_S = 10.0
#: continuous mode without any frame for this long is a WARN
NO_FRAMES_WARN_S = 5.0
_COUNTERS = ("frames_received", "frames_processed", "frames_dropped", "decode_errors",
             "queries", "fixes", "flagged_fixes", "query_errors", "relocalize_requests",
             "map_reloads", "map_reload_failures", "status_fix", "verified",
             "relocalize_abandoned")


class Throttle:
    """``ready()`` is true at most once per ``period_s`` (for throttled log lines)."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._last = -float("inf")

    def ready(self) -> bool:
        now = time.monotonic()
        if now - self._last >= self.period_s:
            self._last = now
            return True
        return False


class RuntimeStats:
    """Thread-safe statistics; :meth:`report` gives (level, message, key/values)."""

    def __init__(self, prior_provider: str, mode: str) -> None:
        self._lock = threading.Lock()
        self.started = time.monotonic()
        self.prior_provider, self.mode = prior_provider, mode
        self.counts = dict.fromkeys(_COUNTERS, 0)
        self.last_frame: float | None = None
        self.last_error = ""
        self.last_error_at: float | None = None
        self.last_decode_error_at: float | None = None
        self.last: dict[str, Any] = {}
        self.last_failed = False

    def frame_received(self, replaced_unused: bool) -> None:
        with self._lock:
            self.counts["frames_received"] += 1
            self.counts["frames_dropped"] += int(replaced_unused)
            self.last_frame = time.monotonic()

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counts[name] += n

    def decode_error(self, message: str) -> None:
        with self._lock:
            self.counts["decode_errors"] += 1
            self.last_error = message
            self.last_error_at = self.last_decode_error_at = time.monotonic()

    def record(self, hyp: Hypothesis | None, error: str, timings_ms: dict[str, float]) -> None:
        """Account one finished query (``hyp`` None: no fix, ``error`` says why)."""
        with self._lock:
            if hyp is None:
                if error and not error.startswith("undecodable"):
                    self.counts["query_errors"] += 1
                    self.last_error, self.last_error_at = error, time.monotonic()
                    self.last_failed = True
                return
            self.last_failed = False
            self.counts["queries"] += 1
            self.counts["fixes"] += 1
            self.counts["flagged_fixes"] += int(hyp.flagged)
            self.counts["status_fix"] += int(hyp.status == "fix")
            self.counts["verified"] += int(hyp.verification == "verified")
            pr = hyp.prior_result
            self.last = {
                "lat": hyp.lat, "lon": hyp.lon, "sigma_m": horizontal_sigma(hyp),
                "status": "STATUS_FIX" if hyp.status == "fix" else "STATUS_NO_FIX",
                "status_reason": hyp.status_reason, "verification": hyp.verification or "none",
                "p_correct": hyp.p_correct, "inliers": hyp.inliers,
                "inlier_ratio": hyp.inlier_ratio,
                "protection_m": hyp.protection_m,  # integrity: error bound at risk 1e-3
                "radius68_m": hyp.uncertainty_m, "radius95_m": hyp.radius95_m,
                "confidence": hyp.confidence, "fusion": hyp.fusion or "none",
                "ref_id": hyp.ref_id, "submap": hyp.submap, "candidates": len(hyp.candidates),
                "flags": "|".join(hyp.flags) or "none", "flagged": hyp.flagged,
                "prior_source": hyp.prior.source if hyp.prior else (pr.source if pr else "none"),
                "prior_ok": bool(pr and pr.ok),
                "prior_reason": (pr.reason if pr else "") or ("ok" if pr and pr.ok else ""),
                "prior_parse": str(pr.extra.get("parse_path") or "") if pr else "",
                "prior_latency_s": pr.latency_s if pr else 0.0,
                **{k: round(v, 2) for k, v in timings_ms.items()},
                "at": time.monotonic(),
            }

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return {**self.counts, "last": dict(self.last), "last_error": self.last_error}

    def report(self, busy: bool = False) -> tuple[str, str, dict[str, Any]]:
        """Level ("OK"/"WARN"/"ERROR"), one-line message and values for /diagnostics."""
        now = time.monotonic()
        with self._lock:
            c, last = dict(self.counts), dict(self.last)
            values: dict[str, Any] = {"mode": self.mode, "prior_provider": self.prior_provider,
                                      **c, "query_in_progress": busy}
            values["last_frame_age_s"] = (None if self.last_frame is None
                                          else round(now - self.last_frame, 3))
            at = last.pop("at", None)
            values.update({f"last_{k}" if k in ("lat", "lon", "sigma_m") else k: v
                           for k, v in last.items()})
            values["last_fix_age_s"] = None if at is None else round(now - at, 3)
            values["last_error"] = self.last_error
            values["last_error_age_s"] = (None if self.last_error_at is None
                                          else round(now - self.last_error_at, 3))
            recent_decode = (self.last_decode_error_at is not None
                             and now - self.last_decode_error_at < RECENT_ERROR_S)
            failed = self.last_failed
        if failed:
            return "ERROR", f"last query failed: {values['last_error']}", values
        silent = now - (self.last_frame if self.last_frame is not None else self.started)
        if self.mode == "continuous" and silent > NO_FRAMES_WARN_S:
            return "WARN", (f"no images for {silent:.0f} s" if c["frames_received"]
                            else "no images received"), values
        if recent_decode:
            return "WARN", f"undecodable frames ({c['decode_errors']}): {values['last_error']}", \
                values
        if not last:
            return "OK", ("waiting for a relocalize request" if self.mode == "on_trigger"
                          else "waiting for the first fix"), values
        what = (f"no prior ({last['prior_reason'] or 'none'}), global retrieval"
                if not last["prior_ok"] else f"prior {last['prior_source']}")
        if last["status"] != "STATUS_FIX":  # the same status and sigma as the published fix
            flags = f" [{last['flags']}]" if last["flagged"] else ""
            return "WARN", (f"no precise fix: STATUS_NO_FIX ({last['status_reason']}), "
                            f"sigma {last['sigma_m']:.0f} m, {what}{flags}"), values
        if last["status_reason"]:  # published as a fix only by fallback_status: fix
            return "WARN", (f"no precise fix: STATUS_FIX ({last['status_reason']}), "
                            f"sigma {last['sigma_m']:.0f} m, {what}"), values
        if last["flagged"]:
            return "WARN", (f"flagged fix [{last['flags']}]: {what}, STATUS_FIX, "
                            f"sigma {last['sigma_m']:.0f} m"), values
        return "OK", (f"fix {last['lat']:.5f}, {last['lon']:.5f} STATUS_FIX sigma "
                      f"{last['sigma_m']:.0f} m, p_correct {last['p_correct']:.3f}, prior "
                      f"{last['prior_source']}, submap {last['submap']}"), values


def map_values(pipe: Any, map_dir: str, fusion: str) -> dict[str, Any]:
    """The diagnostics' values that describe the map in use (``pipe``, a LocalizationPipeline):
    folder, descriptor, fusion, calibration, verification, size and generation."""
    return {"map_dir": map_dir, "descriptor": pipe.descriptor.name, "fusion": fusion,
            "calibration": pipe.localizer.calibration_source,
            "verification": pipe.verifier.unavailable or "on, p_correct calibrated by "
            + pipe.verifier.calibration_source,
            "map_references": pipe.map.n_references,
            "map_generation": pipe.map.manifest.get("generation", 0)}
