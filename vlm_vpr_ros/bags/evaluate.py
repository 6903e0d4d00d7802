"""``vlm-vpr evaluate-bag``: localize every camera frame of a bag against a map, offline.

Images and ground truth come straight from the bag (no ROS graph): each frame is paired with the
``NavSatFix`` nearest in time (header stamps; at most ``max_gt_gap_s`` apart), localized, and the
run writes ``frames.csv``, ``summary.json``, ``world_map.png``, ``error_cdf.png`` and a results
bag ``estimates/`` with the estimated ``NavSatFix`` stream (plus the prior and the paired ground
truth) stamped like the input frames, to view next to it in Foxglove.
"""

from __future__ import annotations

import bisect
import collections
import dataclasses
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from vlm_vpr_ros.bags.frames import (MAX_GT_SIGMA_M, Frame, GroundTruth, iter_frames,
                                     read_ground_truth)
from vlm_vpr_ros.bags.reader import BagReader
from vlm_vpr_ros.errors import BagError, VlmVprError
from vlm_vpr_ros.files.csvio import write_csv_atomic
from vlm_vpr_ros.evaluation.integrity import integrity_report, trials_from_frames, write_report
from vlm_vpr_ros.evaluation.metrics import errors_km, fix_metrics, summarize
from vlm_vpr_ros.files.atomic import atomic_write_json
from vlm_vpr_ros.priors.provider import PriorProvider, PriorQuery, wait_prior

log = logging.getLogger(__name__)

#: ``stamp`` is ``sec.nanosec`` and ``stamp_ns`` the integer nanoseconds: both exact, to join on
FRAME_FIELDS = ["index", "stamp", "stamp_ns", "key", "gt_lat", "gt_lon", "gt_gap_s", "lat",
                "lon", "error_km", "prior_lat", "prior_lon", "prior_source", "prior_reason",
                 "prior_parse", "submap", "ref_id", "uncertainty_m", "radius95_m", "fusion",
                 "n_candidates", "flags", "status", "p_correct", "inliers", "descriptor_ms",
                 "retrieval_ms", "rerank_ms", "verify_ms", "prior_latency_s", "protection_m"]
EST_TOPIC, PRIOR_TOPIC, GT_TOPIC = "/vlm_vpr/fix", "/vlm_vpr/prior", "/vlm_vpr/ground_truth"
FRAME_ID = "vlm_vpr"


@dataclass(frozen=True)
class BagEvalConfig:
    image_topic: str | None = None  # None: the bag's only Image/CompressedImage topic
    gt_topic: str | None = None  # None: the bag's only NavSatFix topic
    max_gt_gap_s: float = 0.5  # frames with no fix this close in time are not scored
    max_frames: int | None = None
    prior_timeout_s: float = 60.0
    window: int = 4  # prior requests in flight ahead of the descriptor work
    alert_limit_m: float = 50.0  # of the integrity report (docs/evaluation.md "Integrity")


def stamp_text(stamp_ns: int) -> str:
    """``sec.nanosec`` (9 digits) of an integer stamp, exact (never through a float)."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return f"{sec}.{nsec:09d}"


def _pair(gt: GroundTruth, t_ns: int, max_gap_s: float) -> tuple[int | None, float | None]:
    if not gt.stamps:
        return None, None
    i = bisect.bisect_left(gt.stamps, t_ns)
    best = min((j for j in (i - 1, i) if 0 <= j < len(gt.stamps)),
               key=lambda j: abs(gt.stamps[j] - t_ns))
    gap = abs(gt.stamps[best] - t_ns) / 1e9
    return (best, gap) if gap <= max_gap_s else (None, gap)


def _with_priors(frames: Iterator[Frame], provider: PriorProvider,
                 window: int) -> Iterator[tuple[Frame, Any]]:
    """Ask the prior for up to ``window`` frames ahead of the one being localized."""
    pending: collections.deque = collections.deque()
    for frame in frames:
        fut = None
        if frame.rgb is not None:
            fut = provider.request(PriorQuery(image=frame.rgb, encoded=frame.encoded,
                                              key=frame.key))
        pending.append((frame, fut))
        if len(pending) > max(0, window):
            yield pending.popleft()
    while pending:
        yield pending.popleft()


def evaluate_bag(bag: BagReader, pipeline: Any, provider: PriorProvider,
                 out_dir: str | os.PathLike[str], config: BagEvalConfig | None = None,
                 progress: bool = True, plots: bool = True, overwrite: bool = False) -> dict:
    """Run the whole evaluation; returns ``{"n", "accuracy", "median_km", "details"}``.

    ``out_dir`` is written next to itself and swapped in when complete
    (:mod:`vlm_vpr_ros.files.outputs`): never inside the bag, and an existing folder is replaced
    only with ``overwrite`` and only when it is an earlier evaluation."""
    from vlm_vpr_ros.files.outputs import StagedOutput, check_not_inside

    check_not_inside(out_dir, [bag.path])
    with StagedOutput(out_dir, "evaluation", overwrite, marker=True) as stage:
        try:
            result = _evaluate(bag, pipeline, provider, stage.path, Path(out_dir), config,
                               progress, plots)
        except _NoUsableFrame as exc:
            stage.commit()  # frames.csv holds the per-frame reasons: keep it
            raise BagError(f"{exc} (per-frame reasons in {Path(out_dir) / 'frames.csv'})") \
                from None
        stage.commit()
    return result


class _NoUsableFrame(BagError):
    pass


def _evaluate(bag: BagReader, pipeline: Any, provider: PriorProvider, out: Path, final: Path,
              config: BagEvalConfig | None, progress: bool, plots: bool) -> dict:
    from vlm_vpr_ros.bags.messages import IMAGE_TYPES, NAVSATFIX

    cfg = config or BagEvalConfig()
    img = bag.find_topic(IMAGE_TYPES, cfg.image_topic, "camera images")
    gt_info = bag.find_topic((NAVSATFIX,), cfg.gt_topic, "ground truth")
    gt = read_ground_truth(bag, gt_info.name)
    if not gt.stamps:
        log.warning("%s: no usable fix on %s; frames cannot be scored", bag.path, gt_info.name)
    total = img.count if cfg.max_frames is None else min(img.count or 0, cfg.max_frames)
    frames = iter_frames(bag, img.name, cfg.max_frames)
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, total=total, desc="evaluate-bag", unit="frame", disable=None)
    rows: list[dict] = []
    est_msgs: list[tuple] = []
    errors: list[str] = []
    for frame, fut in _with_priors(frames, provider, cfg.window):
        row, est = _localize_frame(frame, fut, pipeline, provider, gt, cfg, errors)
        rows.append(row)
        est_msgs.append(est)
    _write_csv(out / "frames.csv", rows)
    decoded = sum(1 for r in rows if "image_error" not in r["flags"])
    if rows and decoded == 0:
        raise _NoUsableFrame(f"none of the {len(rows)} frames on {img.name} could be used; "
                             f"first error: {errors[0] if errors else 'unknown'}")
    scored = [r for r in rows if r["gt_lat"] != ""]
    errs = [None if r["error_km"] == "" else float(r["error_km"]) for r in scored]
    summary = {**summarize(errs),
               "fixes": fix_metrics([r["status"] for r in scored], errs)}
    outputs = {"frames_csv": "frames.csv", "summary_json": "summary.json"}
    summary["integrity"], trials = _integrity(rows, cfg.alert_limit_m)
    if plots:
        outputs.update({k: Path(v).name for k, v in write_report(
            out, summary["integrity"], trials, bag.path.name, staged=False,
            final_dir=final).items()})
    if est_msgs:
        _write_estimates(out / "estimates", est_msgs)
        outputs["estimates_bag"] = "estimates"
    if plots and scored:
        outputs.update({k: Path(v).name for k, v in _plots(out, scored, summary,
                                                           bag.path).items()})
    outputs = {k: str(final / v) for k, v in outputs.items()}  # where they are after the swap
    details = {
        "bag": str(bag.path), "image_topic": img.name, "gt_topic": gt_info.name,
        "frames": len(rows), "frames_scored": len(scored),
        "frames_without_gt": len(rows) - len(scored),
        "frames_failed": len(rows) - decoded, "bag_complete": bag.complete,
        "gt_fixes_too_uncertain": gt.too_uncertain,
        "warnings": list(bag.problems) + _gt_warnings(gt) + errors[:5], "outputs": outputs,
    }
    result = {**summary, "details": details}
    atomic_write_json(out / "summary.json", result)
    return result


def _gt_warnings(gt: GroundTruth) -> list[str]:
    if not gt.too_uncertain:
        return []
    return [f"{gt.too_uncertain} ground-truth fix(es) on {gt.topic} with a sigma above "
            f"{MAX_GT_SIGMA_M:g} m (their own covariance) were not used: frames paired only "
            "with them are not scored"]


def _integrity(rows: list[dict], alert_limit_m: float) -> tuple[dict, list]:
    """The integrity report of every frame (time from the frame stamps: TTFF, gaps)."""
    trials = trials_from_frames(rows)
    return integrity_report(trials, alert_limit_m), trials


def _localize_frame(frame: Frame, fut: Any, pipeline: Any, provider: PriorProvider,
                    gt: GroundTruth, cfg: BagEvalConfig, errors: list[str]) -> tuple[dict, tuple]:
    gi, gap = _pair(gt, frame.stamp_ns, cfg.max_gt_gap_s)
    row = {k: "" for k in FRAME_FIELDS}
    row.update({"index": frame.index, "stamp": stamp_text(frame.stamp_ns),
                "stamp_ns": int(frame.stamp_ns), "key": frame.key,
                "gt_gap_s": "" if gap is None else f"{gap:.3f}"})
    truth = None
    if gi is not None:
        truth = (gt.lat[gi], gt.lon[gi])
        row.update({"gt_lat": f"{truth[0]:.7f}", "gt_lon": f"{truth[1]:.7f}"})
    hyp = None
    if frame.rgb is None:
        row.update({"flags": "image_error", "prior_reason": frame.error})
        errors.append(f"frame {frame.index}: {frame.error}")
    else:
        try:
            hyp = pipeline.localize_image(frame.rgb, wait_prior(fut, provider.name,
                                                           cfg.prior_timeout_s))
        except VlmVprError as exc:
            row.update({"flags": "error", "prior_reason": str(exc)})
            errors.append(f"frame {frame.index}: {exc}")
        except Exception as exc:  # noqa: BLE001 - one bad frame must not lose the others
            log.warning("frame %d: internal error %s: %s", frame.index, type(exc).__name__, exc)
            row.update({"flags": "error", "prior_reason": f"internal error: "
                                                          f"{type(exc).__name__}: {exc}"})
            errors.append(f"frame {frame.index}: {type(exc).__name__}: {exc}")
    if hyp is not None:
        row.update(hyp.as_row())
        row.update({k: f"{v:.2f}" for k, v in hyp.timings_ms.items() if k in row})
        if hyp.prior_result is not None:
            row["prior_latency_s"] = f"{hyp.prior_result.latency_s:.3f}"
        if truth is not None:
            row["error_km"] = f"{errors_km([(hyp.lat, hyp.lon)], [truth])[0]:.4f}"
    # the estimates bag needs the hypothesis, not its candidate list
    slim = None if hyp is None else dataclasses.replace(hyp, candidates=[])
    return row, (frame.stamp_ns, slim, truth)


def _write_csv(path: Path, rows: list[dict]) -> None:
    write_csv_atomic(path, FRAME_FIELDS, rows)


def _write_estimates(path: Path, items: list[tuple]) -> Path:
    """The results bag. Estimates are built exactly as the node publishes them
    (:func:`msg_adapters.navsat.navsat_fix`: flagged fallbacks are ``STATUS_NO_FIX``)."""
    from msg_adapters.navsat import navsat_fix

    from vlm_vpr_ros.bags.messages import NAVSATFIX, navsatfix_msg
    from vlm_vpr_ros.bags.writer import BagWriter

    with BagWriter(path, overwrite=True) as bag:
        for topic in (EST_TOPIC, PRIOR_TOPIC, GT_TOPIC):
            bag.add_topic(topic, NAVSATFIX)
        for t, hyp, truth in items:
            if hyp is not None:
                bag.write(EST_TOPIC, navsat_fix(hyp, t, FRAME_ID), t)
                if hyp.prior is not None:
                    bag.write(PRIOR_TOPIC, navsatfix_msg(hyp.prior.lat, hyp.prior.lon, t,
                                                         FRAME_ID), t)
            if truth is not None:
                bag.write(GT_TOPIC, navsatfix_msg(truth[0], truth[1], t, "gps"), t)
    return path


def _plots(out: Path, rows: list[dict], summary: dict, name: Path) -> dict:
    from vlm_vpr_ros.evaluation.plots import plot_error_cdf, plot_world_map

    gt = [(float(r["gt_lat"]), float(r["gt_lon"])) for r in rows]
    est = [None if r["lat"] == "" else (float(r["lat"]), float(r["lon"])) for r in rows]
    prior = [None if r["prior_lat"] == "" else (float(r["prior_lat"]), float(r["prior_lon"]))
             for r in rows]
    errs = [None if r["error_km"] == "" else float(r["error_km"]) for r in rows]
    acc = summary["accuracy"]
    title = (f"{name.name}: {summary['n']} frames, "
             + ", ".join(f"{k} {v:.0f}%" for k, v in acc.items()))
    world = plot_world_map(out / "world_map.png", gt, est, prior, title=title)
    cdf = plot_error_cdf(out / "error_cdf.png", {"estimate": errs}, title=name.name)
    return {"world_map_png": str(world), "error_cdf_png": str(cdf)}

