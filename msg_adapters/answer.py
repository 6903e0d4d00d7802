"""``vlm_vpr_interfaces`` messages (``Answer``, ``Candidate``, ``Candidates``) from the pure
runtime's :class:`~vlm_vpr_ros.runtime.relocalize.RelocalizeResult` and an outcome's
:class:`~msg_adapters.navsat.FixFields`: the typed form of what the ``fix`` NavSatFix and the
Trigger services' sentence say (same numbers, same stamp). Message classes are imported
inside the functions: the package is optional (``make setup`` builds it)."""

from __future__ import annotations

import math
from typing import Any

from msg_adapters.navsat import STATUS_FIX, STATUS_NO_FIX, FixFields
from vlm_vpr_ros.runtime.relocalize import OUTCOMES, RelocalizeResult, outcome_summary

#: candidates carried by an answer (the best ones; ~/candidates carries the same)
MAX_CANDIDATES = 20


def _nan(v: Any) -> float:
    return math.nan if v is None else float(v)


def candidate_msgs(hyp: Any, limit: int = MAX_CANDIDATES) -> list[Any]:
    from vlm_vpr_interfaces.msg import Candidate

    out = []
    for rank, c in enumerate(hyp.candidates[:limit], 1):
        out.append(Candidate(
            rank=rank, reference_id=str(c.ref_id), submap=str(c.submap),
            latitude=float(c.lat), longitude=float(c.lon), l2_sq=float(c.l2_sq),
            posterior=_nan(c.posterior),
            prior_distance_m=_nan(None if c.prior_km is None else c.prior_km * 1000.0),
            inliers=int(c.inliers if c.inliers is not None else -1)))
    return out


def answer_msg(res: RelocalizeResult, fields: FixFields | None, frame_id: str = "",
               message: str = "") -> Any:
    """An ``Answer`` for one relocalize caller (``fields``: the published fix's fields, None
    without a hypothesis). header.stamp = the answered frame's stamp = the NavSatFix's."""
    from vlm_vpr_interfaces.msg import Answer

    msg = Answer()
    msg.outcome = OUTCOMES.index(res.code)
    msg.status = STATUS_NO_FIX
    for name in ("latitude", "longitude", "altitude", "sigma_m", "protection_m", "p_correct",
                 "p_correct_without_prior"):
        setattr(msg, name, math.nan)
    msg.header.frame_id = frame_id
    out = res.outcome
    msg.message = message
    if out is None:
        msg.reason = message
        return msg
    stamp = int(out.frame.stamp_ns)
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp // 1_000_000_000, stamp % 1_000_000_000
    msg.query_s = float(max(0.0, out.finished - out.started))
    hyp = out.hypothesis
    if hyp is None or fields is None:
        msg.reason = out.error or message
        return msg
    msg.success = bool(fields.precise)
    msg.status = STATUS_FIX if fields.status == STATUS_FIX else STATUS_NO_FIX
    msg.status_reason = fields.reason
    msg.latitude, msg.longitude, msg.altitude = fields.latitude, fields.longitude, fields.altitude
    msg.sigma_m = float(fields.sigma_m)
    # added by the integrity work on its branch (NaN = none); read so either order merges
    msg.protection_m = float(getattr(hyp, "protection_m", math.nan))
    msg.p_correct = float(hyp.p_correct)
    msg.p_correct_without_prior = float(hyp.p_correct_without_prior)
    msg.flags = [str(f) for f in hyp.flags]
    msg.reference_id, msg.submap = str(hyp.ref_id), str(hyp.submap)
    msg.prior_source = hyp.prior.source if hyp.prior is not None else ""
    msg.reason = "" if fields.precise else (fields.reason or "not a fix")
    msg.candidates = candidate_msgs(hyp)
    if not message:
        msg.message = outcome_summary(out, res.waited_s)[1]
    return msg


def candidates_msg(answer: Any) -> Any:
    """``~/candidates``: the typed answer (with its candidates) under the frame's stamp."""
    from vlm_vpr_interfaces.msg import Candidates

    msg = Candidates()
    msg.header = answer.header
    msg.answer = answer
    return msg
