#!/usr/bin/env python3
"""vlm_vpr_node under a 30 Hz camera with a slow VLM: intake, queries, fix latency, memory.

A map of the 71 shipped demo images is built (default descriptor), the node runs as a separate
process (continuous mode) with the ``openai`` prior pointed at the loopback chat-completions
fixture (tests/chat_server.py) answering after ``--vlm-delay`` seconds, and this script publishes
640x480 rgb8 frames at ``--hz`` for ``--duration`` seconds (reliable QoS, loopback DDS). It
records every NavSatFix (stamp → arrival latency) and the node's final /diagnostics.

    .venv/bin/python benchmarks/bench_node.py [--duration 60] [--hz 30] [--vlm-delay 3]

``--debug-ratio`` runs the node twice in one invocation, ``publish_debug`` off then on (same
camera, VLM and map), and prints the node's CPU per processed frame in both runs, their ratio,
and the debug images received per processed frame:

    .venv/bin/python benchmarks/bench_node.py --debug-ratio --duration 30 --vlm-delay 0.2 \
        --min-period 0.5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

from chat_server import ChatServer  # noqa: E402
from node_harness import GraphClient, NodeProcess, domain_id, image_msg, stamp_of  # noqa: E402
from vlm_vpr_ros.evaluation.demo import DEMO_DATA  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.mapping.build_images import build_map  # noqa: E402

QUERY = "546314506564628.jpg"
TRUTH = (39.55910238557, 8.8888751944543)


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(round(q * (len(s) - 1))))]


def run(args: argparse.Namespace, tmp: Path, publish_debug: bool = False) -> dict:
    t0 = time.perf_counter()
    if not (tmp / "map").exists():
        build_map(DEMO_DATA / "images", DEMO_DATA / "coords.csv", tmp / "map",
                  descriptor=args.descriptor, partition="kmeans", clusters=8, progress=False)
    build_s = time.perf_counter() - t0
    frame = cv2.resize(load_image(DEMO_DATA / "images" / QUERY), (640, 480),
                       interpolation=cv2.INTER_AREA)
    dom = domain_id()
    with ChatServer("slow", lat=TRUTH[0] + 0.05, lon=TRUTH[1], delay_s=args.vlm_delay) as srv:
        node = NodeProcess({"map_dir": str(tmp / "map"), "prior_provider": "openai",
                            "prior.base_url": srv.base_url, "prior.max_retries": 0,
                            "prior.timeout_s": args.vlm_delay + 30.0,
                            "prior_timeout_s": args.vlm_delay + 30.0,
                            "min_period_s": args.min_period, "qos": args.qos,
                            "qos_depth": args.qos_depth, "publish_debug": publish_debug,
                            "reference_images_dir": str(DEMO_DATA / "images"),
                            "diagnostics_period_s": 1.0}, tmp / "node.log", dom)
        node.start()
        client = None
        try:
            client = GraphClient(dom)
            if not client.wait_subscribed(60.0):
                raise SystemExit("node did not come up:\n" + node.log())
            from sensor_msgs.msg import CompressedImage

            debug = client.record(CompressedImage, "/vlm_vpr_node/debug_image/compressed")
            rss_start = node.rss_kib()
            cpu0 = cpu_s(node.pid)
            sent: set[int] = set()
            period, published = 1.0 / args.hz, 0
            t_start = time.monotonic()
            nxt = t_start
            rss_trace, next_rss = [], t_start
            while (now := time.monotonic()) < t_start + args.duration:
                if now >= next_rss:
                    rss_trace.append((round(now - t_start), round(node.rss_kib() / 1024)))
                    next_rss += 10.0
                if now >= nxt:
                    stamp = time.time_ns()
                    client.image_pub.publish(image_msg(frame, stamp))
                    sent.add(stamp)
                    published += 1
                    nxt += period
                else:
                    time.sleep(min(0.002, nxt - now))
            run_s = time.monotonic() - t_start
            t_end_ns = time.time_ns()
            time.sleep(args.vlm_delay + 2.0)  # let the last query finish and report
            cpu = cpu_s(node.pid) - cpu0
            rss_end = node.rss_kib()
            diag = client.latest_diag()
            fixes = list(client.fixes)
            debug_images = len(debug)
        finally:
            if client is not None:
                client.close()
            node.stop()
        vlm_requests = len(srv.requests)
    lat_s = [(arrival - stamp_of(m)) / 1e9 for m, arrival in fixes if stamp_of(m) in sent]
    # while the camera runs the slot always holds a frame < 1/hz old; after it stops the last
    # frame waits for the running query, so the final fix is reported apart
    steady = [(arrival - stamp_of(m)) / 1e9 for m, arrival in fixes
              if stamp_of(m) in sent and arrival <= t_end_ns]
    return {
        "descriptor": args.descriptor, "map_build_s": round(build_s, 1),
        "duration_s": round(run_s, 1), "rate_hz": args.hz, "vlm_delay_s": args.vlm_delay,
        "min_period_s": args.min_period, "qos": args.qos,
                            "qos_depth": args.qos_depth,
        "frames_published": published,
        "frames_received": int(diag.get("frames_received", 0)),
        "frames_processed": int(diag.get("frames_processed", 0)),
        "frames_dropped_by_design": int(diag.get("frames_dropped", 0)),
        "decode_errors": int(diag.get("decode_errors", 0)),
        "vlm_requests": vlm_requests, "queries": int(diag.get("queries", 0)),
        "fixes_received": len(fixes), "flagged_fixes": int(diag.get("flagged_fixes", 0)),
        "fixes_while_camera_runs": len(steady),
        "latency_median_s": round(statistics.median(steady), 3) if steady else None,
        "latency_p95_s": round(pct(steady, 0.95), 3) if steady else None,
        "latency_max_s": round(max(steady), 3) if steady else None,
        "latency_max_all_s": round(max(lat_s), 3) if lat_s else None,
        "descriptor_ms_last": float(diag.get("descriptor_ms", "nan")),
        "node_cpu_pct": round(100.0 * cpu / run_s, 1), "node_cpu_s": round(cpu, 2),
        "publish_debug": publish_debug, "debug_images": debug_images,
        "rss_start_mib": round(rss_start / 1024, 1), "rss_end_mib": round(rss_end / 1024, 1),
        "rss_trace_mib": rss_trace,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--hz", type=float, default=30.0)
    ap.add_argument("--vlm-delay", type=float, default=3.0)
    ap.add_argument("--min-period", type=float, default=1.0)
    ap.add_argument("--descriptor", default="vlad_rootsift")
    ap.add_argument("--qos", default="reliable", choices=["reliable", "best_effort",
                                                          "sensor_data"])
    ap.add_argument("--qos-depth", type=int, default=5)
    ap.add_argument("--json", action="store_true", help="print only the JSON result")
    ap.add_argument("--debug-ratio", action="store_true",
                    help="run with publish_debug off, then on; print the CPU ratio")
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    print(cpuinfo.cpu_line(), file=sys.stderr if args.json else sys.stdout, flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        if args.debug_ratio:
            debug_ratio(run(args, Path(tmp), False), run(args, Path(tmp), True), args,
                        Path(tmp) / "map")
            return
        res = run(args, Path(tmp))
    if args.json:
        print(json.dumps(res))
        return
    rows = [
        ("camera", f"{res['rate_hz']:g} Hz 640x480 rgb8 for {res['duration_s']} s "
                   f"({res['qos']}, depth {res['qos_depth']})"),
        ("VLM", f"loopback chat server, {res['vlm_delay_s']:g} s per answer; "
                f"min_period_s {res['min_period_s']:g}; descriptor {res['descriptor']}"),
        ("frames published / received", f"{res['frames_published']} / "
                                         f"{res['frames_received']}"),
        ("frames processed (queries)", f"{res['frames_processed']} ({res['queries']}; "
                                        f"{res['vlm_requests']} VLM requests)"),
        ("frames dropped by design", f"{res['frames_dropped_by_design']} (latest-frame slot)"),
        ("decode errors", str(res["decode_errors"])),
        ("fixes received (flagged)", f"{res['fixes_received']} ({res['flagged_fixes']})"),
        ("fix latency stamp→arrival", f"median {res['latency_median_s']} s, p95 "
                                      f"{res['latency_p95_s']} s, max {res['latency_max_s']} s "
                                      f"({res['fixes_while_camera_runs']} fixes while the "
                                      "camera ran)"),
        ("latency incl. the last fix", f"max {res['latency_max_all_s']} s (its frame waited in "
                                       "the slot after the camera stopped)"),
        ("descriptor time (last query)", f"{res['descriptor_ms_last']:.0f} ms"),
        ("node CPU", f"{res['node_cpu_pct']} % of one core"),
        ("node RSS start → end", f"{res['rss_start_mib']} → {res['rss_end_mib']} MiB"),
        ("node RSS every 10 s", ", ".join(f"{t}s:{m}" for t, m in res["rss_trace_mib"])),
    ]
    width = max(len(k) for k, _ in rows)
    print(f"| {'measure':<{width}} | value |\n|{'-' * (width + 2)}|-------|")
    for k, v in rows:
        print(f"| {k:<{width}} | {v} |")


def render_cost(map_dir: Path, repeats: int = 20) -> tuple[float, float]:
    """In this process, median ms of one debug picture (render + JPEG, the work publish_debug
    adds per query) and of one query's descriptor + localization, on the same 640x480 frame."""
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.runtime import debug_view

    frame = cv2.resize(load_image(DEMO_DATA / "images" / QUERY), (640, 480),
                       interpolation=cv2.INTER_AREA)
    pipe = LocalizationPipeline.open(map_dir)
    refs = debug_view.ReferenceImages(DEMO_DATA / "images", cache_size=0)  # no cache hits
    hyp = pipe.localize_image(frame)
    t_debug, t_query = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        pipe.localize_image(frame)
        t1 = time.perf_counter()
        picture = debug_view.render(frame, refs.load(hyp.ref_id),
                                    debug_view.caption(hyp, "STATUS_FIX", 30.0))
        debug_view.jpeg(picture)
        debug_view.candidate_rows(hyp)
        t2 = time.perf_counter()
        t_query.append(t1 - t0)
        t_debug.append(t2 - t1)
    return 1e3 * statistics.median(t_debug), 1e3 * statistics.median(t_query)


def debug_ratio(off: dict, on: dict, args: argparse.Namespace, map_dir: Path) -> None:
    """The cost of publish_debug: node CPU per processed frame, off and on, in one run."""
    rows = []
    for res in (off, on):
        n = max(1, res["frames_processed"])
        rows.append((f"publish_debug {'on' if res['publish_debug'] else 'off'}",
                     res["frames_processed"], res["debug_images"], res["node_cpu_s"],
                     res["node_cpu_pct"], 1000.0 * res["node_cpu_s"] / n))
    print(f"camera {args.hz:g} Hz 640x480 rgb8, {args.duration:g} s per run; VLM "
          f"{args.vlm_delay:g} s; min_period_s {args.min_period:g}; load {os.getloadavg()[0]:.1f}")
    print("| run | frames processed | debug images | node CPU s | node CPU % | CPU ms per "
          "processed frame |\n|---|---|---|---|---|---|")
    for name, proc, dbg, cpu, pct_, per in rows:
        print(f"| {name} | {proc} | {dbg} | {cpu:.2f} | {pct_:.1f} | {per:.1f} |")
    print(f"debug images per processed frame (on): "
          f"{on['debug_images'] / max(1, on['frames_processed']):.3f}; (off): "
          f"{off['debug_images']}")
    print(f"CPU per processed frame, on / off: {rows[1][5] / max(1e-9, rows[0][5]):.2f}")
    debug_ms, query_ms = render_cost(map_dir)
    print(f"in-process, same frame: debug picture {debug_ms:.1f} ms vs query (descriptor + "
          f"localization) {query_ms:.1f} ms: ratio {debug_ms / query_ms:.3f}")


if __name__ == "__main__":
    main()
