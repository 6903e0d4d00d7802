#!/usr/bin/env python3
"""Soak: vlm_vpr_node under a 30 Hz robot camera cycling the 34 SF night queries, judged like a
GNSS receiver (docs/evaluation.md, "Integrity").

The node runs as its own process (tests/node_harness.py: rclpy wheels, its own ROS_DOMAIN_ID,
LOCALHOST discovery) on an SF map built from ``../shared/data/sf_night/database`` (cached in
``--cache``). A camera publishes rgb8 frames fitted inside 640x480 (aspect kept, never enlarged)
at ``--hz``, each query held for ``--hold-s`` seconds, cycling the 34 queries for
``--duration`` seconds. The prior is the loopback chat-completions fixture (tests/chat_server.py)
answering the city centre after ``--vlm-delay`` seconds, or none (``--prior none``).

Every published NavSatFix is matched to the query that produced it by its stamp (the node stamps
a fix with its frame's stamp); the integrity report (vlm_vpr_ros/evaluation/integrity.py) counts
fixes, fixes > alert limit off, HMI per fix and per distinct query (scene), availability, time to
first fix and the longest gaps (arrival times, from the camera's start). The node's RSS is
sampled every 10 s: baseline = mean over the first 2 minutes, end = mean of the last 3 samples.

    .venv/bin/python benchmarks/soak_node.py --duration 600 --out /tmp/soak

Writes OUT/soak.json, OUT/integrity.json and OUT/stanford.png (``--overwrite`` replaces an
earlier OUT). The protection level of a fix is the node's own (``protection_m`` of the typed
answer it publishes on ``~/candidates`` with ``publish_debug``), or with ``--pl-source
covariance`` the bound its NavSatFix covariance implies (:func:`protection_from_covariance`,
Gaussian: 3.717 σ at 10⁻³, wider than the PL for a fix whose σ is the 25 m place's).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from chat_server import ChatServer  # noqa: E402
from node_harness import GraphClient, NodeProcess, domain_id, image_msg, stamp_of  # noqa: E402
from vlm_vpr_ros.evaluation import integrity, integrity_tables  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402

SF = Path(os.environ.get("VLM_VPR_SHARED", REPO.parent / "shared")) / "data" / "sf_night"
CITY_CENTRE = (37.7749, -122.4194)
#: integrity risk the protection level is read at (2-D Gaussian error, Rayleigh radius)
INTEGRITY_RISK = 1e-3
RSS_PERIOD_S, RSS_BASELINE_S = 10.0, 120.0


def protection_from_covariance(cov, risk: float = INTEGRITY_RISK) -> float | None:
    """The protection level (m) a NavSatFix's covariance implies. Assumed relation: the
    horizontal error is a circular 2-D Gaussian with σ² the larger of the east/north variances,
    and PL is the radius it exceeds with probability ``risk``: P(r > k σ) = exp(-k²/2), so
    PL = σ·sqrt(-2 ln risk) (3.72 σ at 10⁻³). None for an unusable covariance."""
    try:
        var = max(float(cov[0]), float(cov[4]))
    except (TypeError, ValueError, IndexError):
        return None
    if not math.isfinite(var) or var < 0:
        return None
    return math.sqrt(var) * math.sqrt(-2.0 * math.log(risk))


def fit_inside(rgb: np.ndarray, width: int = 640, height: int = 480) -> np.ndarray:
    """``rgb`` scaled to fit inside width x height, aspect kept, never enlarged."""
    h, w = rgb.shape[:2]
    s = min(1.0, width / w, height / h)
    if s >= 1.0:
        return np.ascontiguousarray(rgb)
    return cv2.resize(rgb, (max(1, round(w * s)), max(1, round(h * s))),
                      interpolation=cv2.INTER_AREA)


def load_queries(root: Path) -> list[tuple[str, tuple[float, float], np.ndarray]]:
    with (root / "queries.csv").open(newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    return [(Path(r["file"]).name, (float(r["lat"]), float(r["lon"])),
             fit_inside(load_image(root / r["file"]))) for r in rows]


def sf_map(cache: Path, root: Path) -> Path:
    """The SF map (kmeans, 10 clusters, default descriptor), built once into ``cache``."""
    from vlm_vpr_ros.mapping.build_images import build_map

    out = cache / "sf_map"
    if not (out / "manifest.json").is_file():
        print(f"building the SF map into {out} (once) ...", flush=True)
        build_map(root, root / "database.csv", out, partition="kmeans", clusters=10,
                  progress=False)
    return out


def rss_summary(trace: list[tuple[float, float]]) -> dict:
    base = [m for t, m in trace if 0 < t <= RSS_BASELINE_S] or [m for _, m in trace[:1]]
    end = [m for _, m in trace[-3:]]
    if not base or not end:
        return {"baseline_mib": None, "end_mib": None, "change_pct": None}
    b, e = statistics.fmean(base), statistics.fmean(end)
    return {"baseline_mib": round(b, 1), "end_mib": round(e, 1),
            "change_pct": round(100.0 * (e - b) / b, 2),
            "overlap": trace[-3][0] <= RSS_BASELINE_S if len(trace) >= 3 else True}


def run(args: argparse.Namespace) -> tuple[dict, list]:
    queries = load_queries(args.data)
    map_dir = args.map or sf_map(args.cache, args.data)
    dom = domain_id()
    params = {"map_dir": str(map_dir), "min_period_s": args.min_period,
              "diagnostics_period_s": 1.0, "qos": "reliable",
              # the node's own protection level of each answer: on ~/candidates (typed Answer)
              "publish_debug": args.pl_source == "answer"}
    server = None
    if args.prior == "vlm":
        server = ChatServer("slow", lat=CITY_CENTRE[0], lon=CITY_CENTRE[1],
                            delay_s=args.vlm_delay, uncertainty_km=5.0).start()
        params.update({"prior_provider": "openai", "prior.base_url": server.base_url,
                       "prior.max_retries": 0, "prior.timeout_s": args.vlm_delay + 30.0,
                       "prior_timeout_s": args.vlm_delay + 30.0})
    else:
        params["prior_provider"] = "none"
    node = NodeProcess(params, args.cache / "soak_node.log", dom).start()
    client = None
    sent: dict[int, int] = {}  # frame stamp -> query index
    try:
        client = GraphClient(dom)
        answers = []
        if args.pl_source == "answer":
            from vlm_vpr_interfaces.msg import Candidates

            answers = client.record(Candidates, "vlm_vpr_node/candidates", 50)
        if not client.wait_subscribed(120.0):
            raise SystemExit("node did not come up:\n" + node.log()[-3000:])
        period = 1.0 / args.hz
        t0_wall = time.time()
        t0 = time.monotonic()
        nxt, next_rss, trace, published = t0, t0, [], 0
        while (now := time.monotonic()) < t0 + args.duration:
            if now >= next_rss:
                trace.append((round(now - t0, 1), round(node.rss_kib() / 1024, 1)))
                next_rss += RSS_PERIOD_S
            if now >= nxt:
                qi = int((now - t0) // args.hold_s) % len(queries)
                stamp = time.time_ns()
                client.image_pub.publish(image_msg(queries[qi][2], stamp))
                sent[stamp] = qi
                published += 1
                nxt += period
            else:
                time.sleep(min(0.002, nxt - now))
        t_end_wall = time.time()
        trace.append((round(time.monotonic() - t0, 1), round(node.rss_kib() / 1024, 1)))
        time.sleep(min(args.vlm_delay, 5.0) + 2.0)  # the running query reports
        diag = client.latest_diag()
        with client.lock:
            fixes = list(client.fixes)
            stated = {stamp_of(m.answer): m.answer.protection_m for m, _ in answers}
    finally:
        if client is not None:
            client.close()
        node.stop()
        if server is not None:
            server.stop()
    trials, unmatched, wider, no_pl = [], 0, 0, 0
    for msg, arrival in fixes:
        qi = sent.get(stamp_of(msg))
        if qi is None:
            unmatched += 1
            continue
        name, truth, _ = queries[qi]
        from_cov = protection_from_covariance(msg.position_covariance)
        pl = stated.get(stamp_of(msg)) if args.pl_source == "answer" else from_cov
        if pl is None or not math.isfinite(pl):
            no_pl += args.pl_source == "answer"
            pl = from_cov
        is_fix = msg.status.status >= 0
        wider += bool(is_fix and from_cov is not None and from_cov >= pl)
        trials.append(integrity.Trial(
            truth, (msg.latitude, msg.longitude), "fix" if is_fix else "no_fix", pl,
            arrival / 1e9, name))
    rep = integrity.integrity_report(trials, args.alert_limit_m, t_start=t0_wall,
                                     t_end=t_end_wall, pl_column=True)
    res = {"duration_s": round(t_end_wall - t0_wall, 1), "hz": args.hz, "hold_s": args.hold_s,
           "prior": args.prior, "vlm_delay_s": args.vlm_delay if args.prior == "vlm" else None,
           "min_period_s": args.min_period, "map": str(map_dir), "queries": len(queries),
           "frame_size": "fitted inside 640x480", "frames_published": published,
           "frames_processed": int(diag.get("frames_processed", 0) or 0),
           "navsatfix_received": len(fixes), "navsatfix_unmatched": unmatched,
           "pl_source": args.pl_source, "answers_without_pl": no_pl,
           "fixes_covariance_bound_at_least_pl": wider,
           "pl_from_covariance": f"sigma * {math.sqrt(-2 * math.log(INTEGRITY_RISK)):.3f} "
                                 f"(integrity risk {INTEGRITY_RISK:g})",
           "integrity": rep, "rss_trace_mib": trace, "rss": rss_summary(trace)}
    return res, trials


def print_result(res: dict) -> None:
    rep, rss = res["integrity"], res["rss"]
    print(integrity_tables.format_report(
        rep, f"soak: {res['duration_s']} s, {res['hz']:g} Hz camera (640x480 fit), "
             f"{res['queries']} SF night queries held {res['hold_s']:g} s each, prior "
             f"{res['prior']}" + (f" ({res['vlm_delay_s']:g} s)" if res["vlm_delay_s"] else "")))
    print(f"frames published / processed: {res['frames_published']} / "
          f"{res['frames_processed']}; NavSatFix received {res['navsatfix_received']} "
          f"(unmatched {res['navsatfix_unmatched']})")
    if res["pl_source"] == "answer":
        print(f"protection level: the node's own (protection_m of the typed answer on "
              f"~/candidates; {res['answers_without_pl']} answers without one: from the "
              f"covariance); fixes whose covariance bound ({res['pl_from_covariance']}) is at "
              f"least their PL: {res['fixes_covariance_bound_at_least_pl']}")
    else:
        print(f"protection level from the covariance: {res['pl_from_covariance']}")
    ch = rss["change_pct"]
    print(f"node RSS: baseline (first {RSS_BASELINE_S:.0f} s) {rss['baseline_mib']} MiB, end "
          f"{rss['end_mib']} MiB: {'-' if ch is None else f'{ch:+.2f}%'}"
          + (" (run shorter than the baseline window + 30 s: they overlap)"
             if rss.get("overlap") else ""))
    print("RSS every 10 s: " + ", ".join(f"{t:g}s:{m:g}" for t, m in res["rss_trace_mib"]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0, help="camera seconds (600)")
    ap.add_argument("--hz", type=float, default=30.0)
    ap.add_argument("--hold-s", type=float, default=1.0, help="seconds per query (1.0)")
    ap.add_argument("--prior", choices=["vlm", "none"], default="vlm")
    ap.add_argument("--vlm-delay", type=float, default=2.5)
    ap.add_argument("--min-period", type=float, default=1.0)
    ap.add_argument("--alert-limit-m", default="50")
    ap.add_argument("--data", type=Path, default=SF, help="sf_night folder")
    ap.add_argument("--map", type=Path, default=None, help="an existing SF map")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/vlm_vpr_soak"))
    ap.add_argument("--out", type=Path, default=Path("/tmp/vlm_vpr_soak/out"))
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--json", action="store_true", help="print only the JSON result")
    ap.add_argument("--pl-source", choices=["answer", "covariance"], default="answer",
                    help="protection level per fix: the node's own (typed answer on "
                         "~/candidates, publish_debug on) or read from the NavSatFix "
                         "covariance (sigma * 3.717)")
    args = ap.parse_args(argv)
    args.alert_limit_m = integrity.check_alert_limit(args.alert_limit_m)
    if not (args.data / "queries.csv").is_file():
        print(f"soak_node: {args.data} has no queries.csv (../shared absent?)", file=sys.stderr)
        return 2
    from vlm_vpr_ros.files.outputs import check_target

    check_target(args.out, "evaluation", args.overwrite)  # before the run, not after it
    args.cache.mkdir(parents=True, exist_ok=True)
    res, trials = run(args)
    res["integrity"]["outputs"] = integrity.write_report(
        args.out, res["integrity"], trials, "soak: node, 640x480 camera, SF night",
        overwrite=args.overwrite)
    from vlm_vpr_ros.files.atomic import atomic_write_json

    atomic_write_json(args.out / "soak.json", res)
    if args.json:
        print(json.dumps(res))
    else:
        print_result(res)
        print(f"written: {args.out / 'soak.json'}, "
              f"{res['integrity']['outputs']['stanford_png']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
