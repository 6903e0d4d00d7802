#!/usr/bin/env python3
"""vlm_vpr_node's request paths under a burst: does every caller get an answer, and when?

A map of the 71 shipped demo images is built in a temporary folder (or ``--map`` names one),
the node runs as a separate process (``on_trigger``, the fixed prior, loopback DDS) with a
camera publishing a demo frame at ``--hz``, and this script sends ``--goals`` ``relocalize``
action goals and ``--calls`` ``relocalize_typed`` service calls at once, each with
``timeout_s`` = ``--timeout``, from clients with a deep queue. A caller is *answered* when it
holds its Answer: the typed call's response, or the goal's result (a goal acknowledged but
never finished is not answered). BUSY is ``OUTCOME_BUSY`` (beyond the node's admission limit:
answered at once); results are the other outcomes. The documented worst case (docs/node.md
"Request paths") is ``timeout_s`` + 1 s for every caller.

    .venv/bin/python benchmarks/bench_requests.py [--goals 100] [--calls 100] [--timeout 20]
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

from node_harness import GraphClient, NodeProcess, compressed_msg, domain_id  # noqa: E402
from vlm_vpr_ros.evaluation.demo import DEMO_DATA  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.mapping.build_images import build_map  # noqa: E402

QUERY = "546314506564628.jpg"  # Sanluri, Sardinia (the node tests' frame)
TRUTH = (39.55910238557, 8.8888751944543)
#: a caller's documented worst case: its timeout_s plus this (docs/node.md "Request paths")
SLACK_S = 1.0
OUTCOME_NAMES = ("ANSWERED", "FAILED", "NO_FRAME", "TIMEOUT", "NOT_ACTIVE", "SCHEDULED",
                 "CANCELLED", "BUSY", "REJECTED")


def burst(client: GraphClient, n_goals: int, n_calls: int, timeout_s: float,
          tick: Any) -> dict[str, list[tuple[int | None, float | None]]]:
    """Send the burst; per path, (outcome or None, seconds to the answer or None) per caller."""
    from rclpy.action import ActionClient
    from vlm_vpr_interfaces.action import Relocalize as RelocalizeAction
    from vlm_vpr_interfaces.srv import Relocalize as RelocalizeSrv
    from vlm_vpr_ros.ros.requests import REQUEST_QOS

    ac = ActionClient(client.node, RelocalizeAction, "relocalize",
                      goal_service_qos_profile=REQUEST_QOS,
                      result_service_qos_profile=REQUEST_QOS,
                      cancel_service_qos_profile=REQUEST_QOS)
    srv = client.node.create_client(RelocalizeSrv, "relocalize_typed", qos_profile=REQUEST_QOS)
    assert ac.wait_for_server(timeout_sec=60.0) and srv.wait_for_service(timeout_sec=60.0)
    answered: dict[Any, float] = {}

    def stamp(fut: Any) -> None:
        answered[fut] = time.monotonic()

    results: list[Any] = []

    def on_goal(fut: Any) -> None:  # acknowledged: ask for the result at once
        handle = fut.result()
        if handle is not None and handle.accepted:
            res = handle.get_result_async()
            res.add_done_callback(stamp)
            results.append(res)

    t0 = time.monotonic()
    goals = [ac.send_goal_async(RelocalizeAction.Goal(timeout_s=timeout_s))
             for _ in range(n_goals)]
    for g in goals:
        g.add_done_callback(on_goal)
    calls = [srv.call_async(RelocalizeSrv.Request(timeout_s=timeout_s)) for _ in range(n_calls)]
    for c in calls:
        c.add_done_callback(stamp)
    client.wait_for(lambda: len(results) == sum(g.done() for g in goals) == n_goals
                    and all(r.done() for r in results) and all(c.done() for c in calls),
                    timeout_s + 30.0, tick=tick, period_s=0.1)
    out: dict[str, list[tuple[int | None, float | None]]] = {"action goals": [],
                                                             "typed calls": []}
    for r in results:
        ok = r.done() and r.result() is not None
        out["action goals"].append((r.result().result.answer.outcome if ok else None,
                                    answered[r] - t0 if ok and r in answered else None))
    out["action goals"] += [(None, None)] * (n_goals - len(results))  # never acknowledged
    for c in calls:
        ok = c.done() and c.result() is not None
        out["typed calls"].append((c.result().answer.outcome if ok else None,
                                   answered[c] - t0 if ok and c in answered else None))
    client.node.destroy_client(srv)
    ac.destroy()
    return out


def table(measured: dict[str, list[tuple[int | None, float | None]]],
          timeout_s: float) -> list[str]:
    busy = OUTCOME_NAMES.index("BUSY")
    rows = ["| path | callers | answered | BUSY | results | median s | max s | "
            f"within timeout_s + {SLACK_S:g} s |", "|---|---|---|---|---|---|---|---|"]
    for path, callers in measured.items():
        times = [t for o, t in callers if o is not None and t is not None]
        n_ok = len(times)
        n_busy = sum(o == busy for o, _ in callers)
        kinds = Counter(OUTCOME_NAMES[o] for o, _ in callers if o is not None and o != busy)
        res = ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())) or "0"
        med = f"{statistics.median(times):.2f}" if times else "-"
        mx = max(times) if times else float("inf")
        within = "yes" if n_ok == len(callers) and mx <= timeout_s + SLACK_S else "no"
        rows.append(f"| {path} | {len(callers)} | {n_ok} | {n_busy} | {res} | {med} | "
                    f"{mx:.2f} | {within} |")
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--goals", type=int, default=100, help="relocalize action goals at once")
    ap.add_argument("--calls", type=int, default=100, help="relocalize_typed calls at once")
    ap.add_argument("--timeout", type=float, default=20.0, help="each caller's timeout_s")
    ap.add_argument("--hz", type=float, default=5.0,
                    help="camera rate during the burst (0: a silent camera, callers wait)")
    ap.add_argument("--map", type=Path, default=None, help="an existing map (else built)")
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    print(cpuinfo.cpu_line(), flush=True)
    with tempfile.TemporaryDirectory(prefix="bench_requests_") as tmp:
        map_dir = args.map
        if map_dir is None:
            map_dir = Path(tmp) / "map"
            build_map(DEMO_DATA / "images", DEMO_DATA / "coords.csv", map_dir,
                      descriptor="vlad_rootsift_fast", partition="kmeans", clusters=8,
                      progress=False)
        rgb = load_image(DEMO_DATA / "images" / QUERY)
        ok, png = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
        assert ok
        dom = domain_id()
        params = {"map_dir": str(map_dir), "prior_provider": "fixed",
                  "prior.lat": TRUTH[0] + 0.02, "prior.lon": TRUTH[1] - 0.02,
                  "mode": "on_trigger", "subscribe_raw": False, "subscribe_compressed": True,
                  "diagnostics_period_s": 1.0}
        node = NodeProcess(params, Path(tmp) / "node.log", dom).start()
        client = None
        try:
            client = GraphClient(dom)
            if not client.wait_subscribed(60.0, compressed=True):
                print("node did not subscribe:\n" + node.log()[-3000:], file=sys.stderr)
                return 1
            stamp = [time.time_ns()]
            last = [0.0]

            def tick() -> None:  # the camera, at --hz
                if args.hz > 0 and time.monotonic() - last[0] >= 1.0 / args.hz:
                    last[0] = time.monotonic()
                    stamp[0] += 1_000_000
                    client.compressed_pub.publish(compressed_msg(png.tobytes(), stamp[0],
                                                                 fmt="png"))

            client.wait_for(lambda: False, 1.0 if args.hz > 0 else 0.0, tick=tick)
            measured = burst(client, args.goals, args.calls, args.timeout, tick)
            log = node.log()
        finally:
            if client is not None:
                client.close()
            rc = node.stop()
    digest = hashlib.sha256(png.tobytes()).hexdigest()[:12]
    camera = (f"camera {args.hz:g} Hz (frame {QUERY}, png {digest})" if args.hz > 0
              else "camera silent")
    print(f"# node: on_trigger, fixed prior, {camera}; {args.goals} goals + {args.calls} "
          f"typed calls sent at once, timeout_s {args.timeout:g}; node exit code {rc}")
    print("\n".join(table(measured, args.timeout)))
    if "Traceback" in log:
        print("# the node logged a traceback", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
