#!/usr/bin/env python3
"""Image QoS and transport options: frames received by vlm_vpr_node / frames published.

A camera at ``--hz`` (default 30) publishes ``--width`` x ``--height`` (default 1024x768) rgb8
frames for ``--duration`` seconds to the real node (separate processes, loopback Fast DDS, the
node in ``on_trigger`` mode so it only takes frames in). Each option is one row, all measured in
one run: camera QoS (reliable driver or sensor-data driver), the node's ``qos`` parameter, the
Fast DDS profile (``launch_scripts/fastdds_shm.xml`` in both processes, or the built-in
``FASTDDS_BUILTIN_TRANSPORTS=LARGE_DATA``), and the JPEG ``image/compressed`` topic.
"Received" is the node's ``frames_received`` counter from /diagnostics.

    .venv/bin/python benchmarks/bench_qos.py [--duration 10] [--hz 30] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

from node_harness import NodeProcess, domain_id, ros_env  # noqa: E402

PROFILE = REPO / "launch_scripts" / "fastdds_shm.xml"
QUERY = "546314506564628.jpg"
#: (row name, camera QoS, node qos parameter, transport, compressed)
OPTIONS = [
    ("reliable camera -> node default (best effort)", "reliable", "sensor_data", "default", False),
    ("sensor-data camera -> node default (best effort)", "sensor_data", "sensor_data", "default",
     False),
    ("reliable camera -> node qos:=reliable", "reliable", "reliable", "default", False),
    ("sensor-data camera -> node default, fastdds_shm.xml", "sensor_data", "sensor_data", "shm",
     False),
    ("reliable camera -> node default, fastdds_shm.xml", "reliable", "sensor_data", "shm", False),
    ("sensor-data camera -> node default, LARGE_DATA", "sensor_data", "sensor_data", "large_data",
     False),
    ("sensor-data camera, image/compressed (JPEG q90)", "sensor_data", "sensor_data", "default",
     True),
]


def transport_env(kind: str) -> dict[str, str]:
    if kind == "shm":  # Fast DDS 2.x reads FASTRTPS_*, 3.x FASTDDS_*
        return {"FASTRTPS_DEFAULT_PROFILES_FILE": str(PROFILE),
                "FASTDDS_DEFAULT_PROFILES_FILE": str(PROFILE)}
    if kind == "large_data":
        return {"FASTDDS_BUILTIN_TRANSPORTS": "LARGE_DATA"}
    return {}


def publisher(args: argparse.Namespace) -> None:
    """Child process: the camera. Prints {"published": n, "received": node's counter}."""
    import cv2
    import numpy as np
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import CompressedImage, Image

    from vlm_vpr_ros.evaluation.demo import DEMO_DATA
    from vlm_vpr_ros.files.images import encode_jpeg, load_image

    rgb = cv2.resize(load_image(DEMO_DATA / "images" / QUERY), (args.width, args.height),
                     interpolation=cv2.INTER_AREA)
    rclpy.init()
    node = rclpy.create_node("bench_qos_camera")
    qos = (qos_profile_sensor_data if args.camera_qos == "sensor_data"
           else QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    if args.compressed:
        pub = node.create_publisher(CompressedImage, "image/compressed", qos)
        msg = CompressedImage(format="jpeg", data=encode_jpeg(rgb))
    else:
        pub = node.create_publisher(Image, "image", qos)
        msg = Image(height=args.height, width=args.width, encoding="rgb8", step=args.width * 3)
        msg.data = np.ascontiguousarray(rgb).tobytes()
    latest: dict[str, str] = {}

    def on_diag(arr) -> None:
        latest.update({kv.key: kv.value for kv in arr.status[0].values})
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    deadline = time.monotonic() + 30.0
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    rclpy.spin_once(node, timeout_sec=0.5)
    start = int(latest.get("frames_received", 0) or 0)
    period, sent = 1.0 / args.hz, 0
    t0 = nxt = time.monotonic()
    while (now := time.monotonic()) < t0 + args.duration:
        if now >= nxt:
            stamp = time.time_ns()
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            pub.publish(msg)
            sent += 1
            nxt += period
        rclpy.spin_once(node, timeout_sec=max(0.0, min(0.002, nxt - time.monotonic())))
    end = time.monotonic() + 2.5  # the node reports every 0.5 s
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    print(json.dumps({"published": sent,
                      "received": int(latest.get("frames_received", 0) or 0) - start,
                      "payload_bytes": len(msg.data)}))
    node.destroy_node()
    rclpy.try_shutdown()


def run_option(row, args, map_dir: Path, tmp: Path) -> dict:
    name, camera_qos, node_qos, transport, compressed = row
    dom = domain_id()
    extra = transport_env(transport)
    saved = {k: os.environ.get(k) for k in extra}
    os.environ.update(extra)
    try:
        node = NodeProcess({"map_dir": str(map_dir), "mode": "on_trigger", "qos": node_qos,
                            "subscribe_raw": not compressed, "subscribe_compressed": compressed,
                            "diagnostics_period_s": 0.5}, tmp / f"node_{dom}.log", dom).start()
    finally:
        for k, v in saved.items():
            os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
    try:
        cmd = [sys.executable, __file__, "--publisher", "--camera-qos", camera_qos,
               "--hz", str(args.hz), "--duration", str(args.duration),
               "--width", str(args.width), "--height", str(args.height)]
        cmd += ["--compressed"] if compressed else []
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.duration + 90,
                              env={**ros_env(dom), **extra}, cwd=REPO)
        if proc.returncode != 0:
            raise SystemExit(f"{name}: camera failed:\n{proc.stderr[-2000:]}\n{node.log()}")
        res = json.loads(proc.stdout.strip().splitlines()[-1])
    finally:
        node.stop()
    res.update(option=name, ratio=round(res["received"] / max(1, res["published"]), 3))
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--hz", type=float, default=30.0)
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--height", type=int, default=768)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--publisher", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--camera-qos", default="reliable", help=argparse.SUPPRESS)
    ap.add_argument("--compressed", action="store_true", help=argparse.SUPPRESS)
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    print(cpuinfo.cpu_line(), file=sys.stderr if args.json else sys.stdout, flush=True)
    if args.publisher:
        publisher(args)
        return
    from vlm_vpr_ros.evaluation.demo import DEMO_DATA
    from vlm_vpr_ros.mapping.build_images import build_map

    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        build_map(DEMO_DATA / "images", DEMO_DATA / "coords.csv", tmp / "map",
                  descriptor="vlad_rootsift_fast", partition="kmeans", clusters=8,
                  progress=False)
        rows = [run_option(row, args, tmp / "map", tmp) for row in OPTIONS]
    if args.json:
        print(json.dumps(rows))
        return
    print(f"{args.hz:g} Hz {args.width}x{args.height} for {args.duration:g} s per row "
          f"(raw rgb8 {args.width * args.height * 3 / 1e6:.1f} MB/frame), loopback Fast DDS\n")
    w = max(len(r["option"]) for r in rows)
    print(f"| {'option':<{w}} | received / published | ratio | bytes/frame |")
    print(f"|{'-' * (w + 2)}|---------------------|-------|-------------|")
    for r in rows:
        print(f"| {r['option']:<{w}} | {r['received']:>8} / {r['published']:<9} | "
              f"{r['ratio']:.3f} | {r['payload_bytes']:>11} |")


if __name__ == "__main__":
    main()
