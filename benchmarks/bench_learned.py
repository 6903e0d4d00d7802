#!/usr/bin/env python3
"""The verification presets side by side (issue 42): what each costs and how far its evidence
separates the right place from look-alikes and from noise.

Per preset (``sift``, ``xfeat_lighterglue``, ``xfeat_mnn``, ``disk_lightglue``,
``aliked_lightglue``), on ``--device`` (cpu, or cuda on a GPU machine: the same script):

* ``extract ms``: the median time to extract one image's features (its frame <= 640 px;
  ``sift``: the SIFT of the vlad_rootsift map's own pass, 640 px);
* ``K=20 ms``: per query, matching + MAGSAC against 20 references (median over the queries);
* on SF night (``../shared/data/sf_night``; skipped without it) for the queries 0, 3, 6, ...
  (``--queries N``: the first N of every third query, default 4; DISK and ALIKED cost ~1 s an
  image and a pair on a 2-core CPU, so 10 queries take ~35 min there): the inliers of the
  **true reference** (the database image nearest the query's position) and of the **strongest
  look-alike** (the reference with the most inliers among the top 20 ``vlad_rootsift``
  candidates that lie more than 25 m from the truth): medians, and in how many queries the true
  one has more;
* ``noise``: inliers of ``--pairs`` random pairs of references at least 1 km apart (drawn with
  a fixed seed among the references the queries extracted): median / p95 / p99 / max — the
  matcher's noise level, SIFT's is 12 (docs/verification.md).

``OMP_WAIT_POLICY=PASSIVE`` is set unless the environment says otherwise (see below). Retrieval
uses a vlad_rootsift map of SF night: ``--map DIR``, else one is built in a temporary
folder without local features (about a minute). Without SF night, the timings use the shipped
demo images (each of ``--queries`` images against 20 others) and the evidence columns are
empty.

    nice -n 5 .venv/bin/python benchmarks/bench_learned.py [--device cpu|cuda] [--queries N]
        [--pairs P] [--presets a,b] [--map DIR] [--demo]
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: torch's OpenMP threads spin while they wait; on a shared 2-core host that made XFeat's
#: extraction 10x slower with 2 threads (seconds, against 60-100 ms with PASSIVE): set before
#: torch loads, printed in the threads line (override it in the environment)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.geodesy import haversine_km  # noqa: E402
from vlm_vpr_ros.localization.verification.components import (  # noqa: E402
    create_feature, create_matcher)
from vlm_vpr_ros.localization.verification.geometry import (  # noqa: E402
    GeometryConfig, fundamental_inliers)
from vlm_vpr_ros.localization.verification.presets import (  # noqa: E402
    get_preset, preset_for_map)
from vlm_vpr_ros.mapping.coords_csv import read_coords_csv  # noqa: E402

SHARED = Path(os.environ.get("VLM_VPR_SHARED", REPO.parent / "shared"))
PRESETS = ("sift", "xfeat_lighterglue", "xfeat_mnn", "disk_lightglue", "aliked_lightglue")
K = 20
FAR_M = 25.0
RANDOM_MIN_KM = 1.0
#: the SIFT pass of a vlad_rootsift map (640 px, 1500 keypoints), which its sift preset shares
VLAD_ROOTSIFT = {"name": "vlad_rootsift", "config": {"max_side": 640, "n_features": 1500}}


class Runner:
    """One preset's feature and matcher on a device, with its timings."""

    def __init__(self, name: str, device: str, threads: int) -> None:
        p = preset_for_map(name, VLAD_ROOTSIFT)
        self.preset = p
        fcfg, mcfg = dict(p.feature_config), dict(p.matcher_config)
        if name != "sift":
            fcfg["device"], fcfg["threads"] = device, threads
            if p.matcher != "mnn":
                mcfg["device"], mcfg["threads"] = device, threads
        self.feature = create_feature(p.feature, fcfg)
        self.matcher = create_matcher(p.matcher, mcfg)
        self.geometry = GeometryConfig(**p.geometry)
        self.extract_ms: list[float] = []
        self.cache: dict[str, object] = {}

    def features(self, key: str, image: np.ndarray | None, query: bool = False):
        if key not in self.cache:
            k = self.preset.query_max_keypoints if query else self.preset.max_keypoints
            t = time.perf_counter()
            self.cache[key] = self.feature.extract(image, k)
            self.extract_ms.append((time.perf_counter() - t) * 1e3)
        return self.cache[key]

    def inliers(self, q, refs) -> tuple[list[int], float]:
        """Inliers of each reference and the ms of the matches + MAGSAC fits."""
        t = time.perf_counter()
        prepared = self.matcher.prepare(q)
        out = []
        for r in refs:
            m = self.matcher.match(prepared, q, r)
            out.append(int(fundamental_inliers(q.keypoints[m[:, 0]], r.keypoints[m[:, 1]],
                                               self.geometry).sum()) if len(m) else 0)
        return out, (time.perf_counter() - t) * 1e3


def sf_tasks(map_dir: str | None, work: Path, n_queries: int) -> tuple[list, dict, Path]:
    """Per chosen query: (query key, query image path, true ref id, top-20 candidates as
    (ref id, metres from the truth)); the references' positions; the image root."""
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.mapping.build_images import build_map

    sf = SHARED / "data" / "sf_night"
    if not map_dir:
        print("# building a vlad_rootsift map of SF night for retrieval (no local features)",
              flush=True)
        map_dir = str(work / "sf")
        build_map(sf, sf / "database.csv", map_dir, partition="kmeans", clusters=8,
                  local_features="none", progress=False)
    refs = {f: (lat, lon) for f, lat, lon in read_coords_csv(sf / "database.csv")}
    ids = list(refs)
    rlat = np.array([refs[i][0] for i in ids])
    rlon = np.array([refs[i][1] for i in ids])
    pipe = LocalizationPipeline.open(map_dir, verification={"top_k": 0})
    tasks = []
    for f, lat, lon in read_coords_csv(sf / "queries.csv")[::3][:n_queries]:
        true = ids[int(np.argmin(haversine_km(lat, lon, rlat, rlon)))]
        hyp = pipe.localize_image(load_image(sf / f))
        top = [(c.ref_id, float(haversine_km(lat, lon, c.lat, c.lon)) * 1e3)
               for c in hyp.candidates[:K]]
        tasks.append((f, sf / f, true, top))
    return tasks, refs, sf


def demo_tasks(n_queries: int) -> tuple[list, dict, Path]:
    from vlm_vpr_ros.evaluation.demo import DEMO_DATA

    rows = read_coords_csv(DEMO_DATA / "coords.csv")
    files = [f for f, _, _ in rows]
    tasks = []
    for i in range(min(n_queries, len(files))):
        others = [f for f in files if f != files[i]][i:i + K]
        tasks.append((files[i], DEMO_DATA / "images" / files[i], None,
                      [(f, float("nan")) for f in others]))
    return tasks, {f: (lat, lon) for f, lat, lon in rows}, DEMO_DATA / "images"


def pct(xs: list[int], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else float("nan")


def run_preset(name: str, device: str, threads: int, tasks: list, refs: dict, root: Path,
               pairs: int, real: bool) -> dict:
    r = Runner(name, device, threads)
    warm = r.feature.extract(load_image(tasks[0][1]), 64)  # first calls allocate: not timed
    r.matcher.match(r.matcher.prepare(warm), warm, warm)
    r.extract_ms.clear()
    match_ms, true_in, far_in, wins = [], [], [], 0
    for qkey, qpath, true, top in tasks:
        q = r.features("q:" + qkey, load_image(qpath), query=True)
        keys = [rid for rid, _ in top]
        if true is not None and true not in keys:
            keys = keys[:K - 1] + [true]  # the true reference is matched even if not retrieved
        feats = [r.features(k, load_image(root / k)) for k in keys]
        counts, ms = r.inliers(q, feats)
        match_ms.append(ms)
        if real:
            by = dict(zip(keys, counts))
            far = [by[rid] for rid, d in top if d > FAR_M and rid in by]
            true_in.append(by[true])
            far_in.append(max(far, default=0))
            wins += by[true] > far_in[-1]
    seen = [k for k in r.cache if not k.startswith("q:")]
    rng = random.Random(0)
    noise: list[int] = []
    tries = 0
    while len(noise) < pairs and len(seen) > 1 and tries < 100 * pairs:
        tries += 1
        a, b = rng.sample(seen, 2)
        if refs and float(haversine_km(*refs[a], *refs[b])) < RANDOM_MIN_KM:
            continue
        noise.append(r.inliers(r.cache[a], [r.cache[b]])[0][0])
    return {"preset": name, "device": device, "extract": statistics.median(r.extract_ms),
            "match": statistics.median(match_ms), "true": true_in, "far": far_in,
            "wins": wins, "noise": noise, "images": len(r.extract_ms)}


def row(res: dict, real: bool) -> str:
    med = (lambda xs: f"{statistics.median(xs):.0f}" if xs else "-")
    n = res["noise"]
    noise = (f"{pct(n, 50):.0f} / {pct(n, 95):.0f} / {pct(n, 99):.0f} / {max(n)} ({len(n)})"
             if n else "-")
    ev = (f"{med(res['true'])} | {med(res['far'])} | {res['wins']}/{len(res['true'])}"
          if real else "- | - | -")
    return (f"| {res['preset']} | {res['device']} | {res['extract']:.0f} | {res['match']:.0f} | "
            f"{ev} | {noise} |")


def main() -> int:
    cpuinfo.apply_cpu_paths()
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (learned presets)")
    ap.add_argument("--queries", type=int, default=4,
                    help="every third query, the first N (default 4: ~10 min on a loaded "
                         "2-core CPU; docs/verification.md's table used 10)")
    ap.add_argument("--pairs", type=int, default=50, help="random pairs >= 1 km apart")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch CPU threads of the learned presets (their default 1; 0: torch's)")
    ap.add_argument("--presets", default=",".join(PRESETS))
    ap.add_argument("--map", default=None, help="a vlad_rootsift map of SF night (retrieval)")
    ap.add_argument("--demo", action="store_true",
                    help="the shipped demo images even where SF night is present (timings)")
    cpuinfo.add_argument(ap)
    args = ap.parse_args()
    names = [p for p in args.presets.split(",") if p]
    for p in names:
        get_preset(p)  # an unknown name lists the choices before any work
    real = (SHARED / "data" / "sf_night").is_dir() and not args.demo
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        tasks, refs, root = (sf_tasks(args.map, Path(tmp), args.queries) if real
                             else demo_tasks(args.queries))
        results = []
        for p in names:
            t = time.monotonic()
            results.append(run_preset(p, args.device, args.threads, tasks, refs, root,
                                      args.pairs, real))
            print(f"# {p}: {results[-1]['images']} images, {time.monotonic() - t:.0f} s",
                  flush=True)
    import torch

    print(cpuinfo.cpu_line())
    print(f"# torch {torch.__version__}, threads option {args.threads} (torch's own: "
          f"{torch.get_num_threads()}); device "
          f"{args.device}; {len(tasks)} queries "
          + ("of SF night (every third)" if real else "(demo images: timings only)")
          + f"; K = {K}; {time.monotonic() - t0:.0f} s in all")
    print()
    print("| preset | device | extract ms (median, 640 px) | K=20 match+MAGSAC ms (median) | "
          "true ref inliers (median) | strongest >25 m in top 20 (median) | true > strongest "
          "| noise: random pairs >= 1 km, median / p95 / p99 / max (pairs) |")
    print("|---|---|---|---|---|---|---|---|")
    for res in results:
        print(row(res, real))
    return 0


if __name__ == "__main__":
    sys.exit(main())
