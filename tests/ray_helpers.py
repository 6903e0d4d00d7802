"""Helpers of the Ray tests: a small reference set (SF night subset, or generated images), and a
real two-node Ray cluster on this machine (own temp dir and ports, always torn down)."""

from __future__ import annotations

import csv
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
RAY_BIN = Path(sys.executable).with_name("ray")
#: descriptor of the Ray tests: the fast VLAD preset (fitted, so fit + broadcast are covered)
DESCRIPTOR = "vlad_rootsift_fast"
#: smaller images and fewer keypoints keep the suite's Ray tests within their time budget
DESCRIPTOR_OPTIONS = {"max_side": 320, "n_features": 400}
OBJECT_STORE = 100 * 1024 * 1024


def ray_env() -> dict:
    """Environment of cluster processes and drivers: no token auth (a throwaway local cluster),
    no usage stats, no inherited RAY_ADDRESS."""
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    env.update(RAY_AUTH_MODE="disabled", RAY_USAGE_STATS_ENABLED="0", PYTHONUNBUFFERED="1")
    return env


def make_reference_set(root: Path, shared: Path | None, n: int = 40) -> dict:
    """``root/images`` + ``root/coords.csv`` (+ a corrupt image) and query images.

    With ../shared: every k-th SF night database image (symlinked), the real night queries.
    Without: generated textured images around San Francisco, queries = some of the references."""
    img = root / "images"
    (img / "database").mkdir(parents=True)
    rows, queries = [], []
    sf = shared / "data" / "sf_night" if shared else None
    if sf is not None and (sf / "database.csv").exists():
        with open(sf / "database.csv", newline="") as fh:
            all_rows = list(csv.DictReader(fh))
        step = max(1, len(all_rows) // n)
        for r in all_rows[::step][:n]:
            os.symlink(sf / r["file"], img / r["file"])
            rows.append((r["file"], float(r["lat"]), float(r["lon"])))
        with open(sf / "queries.csv", newline="") as fh:
            queries = [sf / r["file"] for r in list(csv.DictReader(fh))[:4]]
    else:
        rng = np.random.default_rng(0)
        for i in range(n):
            im = _texture(rng, 360, 480)
            name = f"database/gen_{i:03d}.jpg"
            cv2.imwrite(str(img / name), im)
            rows.append((name, 37.70 + 0.1 * rng.random(), -122.50 + 0.1 * rng.random()))
        queries = [img / rows[i][0] for i in range(0, n, n // 4)][:4]
    # one unreadable reference: skipped and listed by both engines
    (img / "database" / "broken.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    rows.insert(len(rows) // 2, ("database/broken.jpg", 37.75, -122.45))
    coords = root / "coords.csv"
    with open(coords, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "lat", "lon"])
        w.writerows(rows)
    return {"images": img, "coords": coords, "rows": rows, "queries": queries}


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    base = rng.integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8)
    im = cv2.resize(base, (w, h), interpolation=cv2.INTER_CUBIC)
    for _ in range(12):
        c = tuple(int(v) for v in rng.integers(0, 256, 3))
        p1 = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.rectangle(im, p1, (p1[0] + int(rng.integers(10, 80)), p1[1] + 40), c, 2)
    return im


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _children(pids: set[int]) -> set[int]:
    """All live descendants of ``pids`` (read from /proc)."""
    parent: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
                parent[int(d.name)] = int(stat.rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    found, grew = set(pids), True
    while grew:
        new = {p for p, pp in parent.items() if pp in found and p not in found}
        found |= new
        grew = bool(new)
    return found - set(pids)


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


class LocalCluster:
    """``ray start --head`` + ``ray start --address`` (a second node) with their own temp dir
    and free ports; ``address`` is HOST:PORT of the head's GCS."""

    def __init__(self, cpus_per_node: int = 1) -> None:
        self.tmp = Path(tempfile.mkdtemp(prefix="r12c_", dir="/tmp"))  # short: socket paths
        self.port = free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.procs: list[subprocess.Popen] = []
        self.cpus = cpus_per_node

    def _start(self, args: list[str], log: str) -> subprocess.Popen:
        common = [f"--num-cpus={self.cpus}", f"--object-store-memory={OBJECT_STORE}",
                  "--node-ip-address=127.0.0.1", "--disable-usage-stats", "--block",
                  f"--dashboard-agent-listen-port={free_port()}",
                  f"--metrics-export-port={free_port()}",
                  f"--runtime-env-agent-port={free_port()}"]
        p = subprocess.Popen([str(RAY_BIN), "start", *args, *common], env=ray_env(),
                             stdout=subprocess.DEVNULL, stderr=open(self.tmp / log, "w"),
                             start_new_session=True)
        self.procs.append(p)
        return p

    def start(self, timeout: float = 60.0) -> "LocalCluster":
        self._start(["--head", f"--port={self.port}", f"--temp-dir={self.tmp}",
                     "--include-dashboard=false", f"--ray-client-server-port={free_port()}"],
                    "head.log")
        deadline = time.monotonic() + timeout
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), 0.5).close()
                break
            except OSError:
                if time.monotonic() > deadline or self.procs[0].poll() is not None:
                    raise RuntimeError("ray head did not start: "
                                       + (self.tmp / "head.log").read_text()[-2000:])
                time.sleep(0.3)
        self._start([f"--address={self.address}"], "worker.log")
        self.wait_nodes(2, deadline)
        return self

    def wait_nodes(self, n: int, deadline: float) -> None:
        code = ("import ray,time,sys\n"
                f"ray.init(address='{self.address}', log_to_driver=False)\n"
                f"while sum(x['Alive'] for x in ray.nodes()) < {n}:\n"
                "    time.sleep(0.3)\n")
        subprocess.run([sys.executable, "-c", code], env=ray_env(), check=True,
                       timeout=max(5.0, deadline - time.monotonic()),
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def worker_pids(self, prefix: str = "ray::MapWorker") -> list[int]:
        """Live actor processes of this cluster whose title starts with ``prefix``."""
        return sorted(p for p in _children({q.pid for q in self.procs})
                      if cmdline(p).startswith(prefix))

    def stop(self) -> None:
        pids = {q.pid for q in self.procs}
        everything = _children(pids)
        for q in self.procs:
            try:
                os.killpg(q.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        for p in everything:  # workers in their own sessions
            try:
                os.kill(p, signal.SIGKILL)
            except ProcessLookupError:
                pass
        for q in self.procs:
            q.wait(timeout=30)
        shutil.rmtree(self.tmp, ignore_errors=True)
