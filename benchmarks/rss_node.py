#!/usr/bin/env python3
"""The node's resident memory under a camera: vlm_vpr_node as its own process
(tests/node_harness.py) on an SF night map, a 30 Hz camera publishing the 34 night queries
fitted inside 640x480 (each held 1 s), the VLM the loopback chat fixture answering after
``--vlm-delay`` s; RSS sampled every 10 s. Prints the trace, the mean of the 2nd minute and of
the last minute, and the change between them (target of issue 29: within +-10 % after the
first 2 minutes; a 30-minute run is ``--duration 1800``).

    .venv/bin/python benchmarks/rss_node.py --map /tmp/$USER/sf_map --duration 600
    MALLOC_ARENA_MAX=16 .venv/bin/python benchmarks/rss_node.py ...   # glibc's default arenas
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import cv2

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from chat_server import ChatServer  # noqa: E402
from node_harness import GraphClient, NodeProcess, image_msg  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.mapping.build_images import read_coords_csv  # noqa: E402

SF = Path(os.environ.get("VLM_VPR_SHARED", REPO.parent / "shared")) / "data" / "sf_night"


def frames(data: Path) -> list:
    out = []
    for f, _, _ in read_coords_csv(data / "queries.csv"):
        rgb = load_image(data / f)
        s = min(1.0, 640 / rgb.shape[1], 480 / rgb.shape[0])
        size = (max(1, round(rgb.shape[1] * s)), max(1, round(rgb.shape[0] * s)))
        out.append(cv2.resize(rgb, size, interpolation=cv2.INTER_AREA))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", type=Path, required=True, help="an SF night map")
    ap.add_argument("--data", type=Path, default=SF)
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--hz", type=float, default=30.0)
    ap.add_argument("--vlm-delay", type=float, default=2.5)
    ap.add_argument("--domain", type=int, default=156)
    ap.add_argument("--qos", default="reliable", help="the node's image QoS (reliable)")
    ap.add_argument("--log", type=Path, default=Path("rss_node.log"))
    a = ap.parse_args()
    imgs = frames(a.data)
    server = ChatServer("slow", lat=37.7749, lon=-122.4194, delay_s=a.vlm_delay,
                        uncertainty_km=5.0).start()
    params = {"map_dir": str(a.map), "min_period_s": 1.0, "qos": a.qos,
              "prior_provider": "openai", "prior.base_url": server.base_url,
              "prior.max_retries": 0, "prior.timeout_s": a.vlm_delay + 30.0,
              "prior_timeout_s": a.vlm_delay + 30.0}
    node = NodeProcess(params, a.log, a.domain).start()
    client = None
    trace: list[tuple[float, float]] = []
    try:
        client = GraphClient(a.domain)
        if not client.wait_subscribed(120.0):
            raise SystemExit("node did not come up:\n" + node.log()[-3000:])
        t0 = time.monotonic()
        nxt = next_rss = t0
        while (now := time.monotonic()) < t0 + a.duration:
            if now >= next_rss:
                trace.append((round(now - t0), round(node.rss_kib() / 1024, 1)))
                print(f"{trace[-1][0]:>5} s  RSS {trace[-1][1]} MiB", flush=True)
                next_rss += 10.0
            if now >= nxt:
                qi = int(now - t0) % len(imgs)
                client.image_pub.publish(image_msg(imgs[qi], time.time_ns()))
                nxt += 1.0 / a.hz
            else:
                time.sleep(min(0.002, nxt - now))
        diag = client.latest_diag()
    finally:
        if client is not None:
            client.close()
        node.stop()
        server.stop()
    second = [m for t, m in trace if 60 <= t < 120]
    last = [m for t, m in trace if t >= trace[-1][0] - 60]
    res = {"duration_s": a.duration, "queries": diag.get("queries"), "qos": a.qos,
           "malloc_arena_max": os.environ.get("MALLOC_ARENA_MAX", "2 (node default)"),
           "rss_2nd_minute_mib": round(statistics.fmean(second), 1) if second else None,
           "rss_last_minute_mib": round(statistics.fmean(last), 1) if last else None}
    if second and last:
        res["change_pct"] = round(100 * (res["rss_last_minute_mib"] / res["rss_2nd_minute_mib"]
                                         - 1), 1)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
