#!/usr/bin/env python3
"""Decode bombs (issue 19): peak RSS of decoding small files that claim huge images, through
OpenCV directly (what the pixel guard let through before: it read only PNG and JPEG headers)
and through :func:`vlm_vpr_ros.files.images.decode_image_bytes` (the header of every format
read by Pillow first), each in a fresh child process; a normal query JPEG as the reference.

Makes its bombs itself: 12000 x 12000 px (1.44e8 px, above the 1e8 budget) TIFF (group 4),
GIF, WebP (lossless) and PNG, each a few KB to a few hundred KB. Making the WebP needs ~1 GB of
RAM for a moment (the encoder's input).

    .venv/bin/python benchmarks/bench_decode_bombs.py [--side 12000] [--workdir /tmp/bombs]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

CHILD = r"""
import json, sys
import cv2, numpy as np
from vlm_vpr_ros.files.images import decode_image_bytes

def hwm_kb():  # this process's own peak RSS (VmHWM starts afresh at exec, unlike ru_maxrss)
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1])

data = open(sys.argv[1], "rb").read()
base = hwm_kb()
result = "decoded"
try:
    if sys.argv[2] == "opencv":
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        result = "decoded" if img is not None else "not decoded"
    else:
        decode_image_bytes(data, sys.argv[1])
except Exception as exc:
    result = "refused (too large)" if "too large" in str(exc) else f"refused: {exc}"[:60]
peak = hwm_kb()
print(json.dumps({"base_mb": base / 1024, "peak_mb": peak / 1024, "result": result}))
"""


def make_bombs(folder: Path, side: int) -> dict[str, Path]:
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    bitmap = Image.new("1", (side, side), 1)
    out["TIFF"] = folder / "bomb.tif"
    bitmap.save(out["TIFF"], compression="group4")
    out["PNG"] = folder / "bomb.png"
    bitmap.save(out["PNG"], optimize=True)
    del bitmap
    pal = Image.new("P", (side, side), 0)
    out["GIF"] = folder / "bomb.gif"
    pal.save(out["GIF"])
    del pal
    rgb = Image.new("RGB", (side, side), (90, 120, 150))
    out["WebP"] = folder / "bomb.webp"
    rgb.save(out["WebP"], lossless=True, quality=0, method=0)
    del rgb
    demo = sorted((REPO / "vlm_vpr_ros" / "data" / "osv5m_demo" / "images").iterdir())[0]
    out["query JPEG"] = folder / "query.jpg"
    shutil.copy(demo, out["query JPEG"])
    return out


def measure(path: Path, how: str) -> dict:
    r = subprocess.run([sys.executable, "-c", CHILD, str(path), how], capture_output=True,
                       text=True, timeout=600, cwd=REPO)
    if r.returncode != 0:
        return {"base_mb": float("nan"), "peak_mb": float("nan"),
                "result": f"child failed ({r.returncode}): {r.stderr.strip()[-80:]}"}
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=12000)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_decode_bombs"))
    ap.add_argument("--keep", action="store_true")
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    print(cpuinfo.cpu_line(), flush=True)
    files = make_bombs(args.workdir, args.side)
    print(f"{args.side}x{args.side} px bombs; load {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} CPUs; peak RSS of a fresh child: after reading the file / after "
          "decoding")
    print(f"{'file':<12}{'bytes':>10}  {'OpenCV directly (MB)':>22}  "
          f"{'decode_image_bytes (MB)':>24}  result")
    for name, path in files.items():
        a, b = measure(path, "opencv"), measure(path, "guarded")
        print(f"{name:<12}{path.stat().st_size:>10,}  {a['base_mb']:>9.0f} -> {a['peak_mb']:>8.0f}"
              f"  {b['base_mb']:>10.0f} -> {b['peak_mb']:>9.0f}  {b['result']}")
    if not args.keep:
        shutil.rmtree(args.workdir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
