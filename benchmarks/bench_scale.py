#!/usr/bin/env python3
"""Planet-scale benchmark (issue 11): flat vs fp16 vs pq maps of N synthetic 512-D references.

Makes its own data, out of core (nothing of size N x dim is ever held in RAM):
- positions: the MP-16 coordinates of ../shared/data/mp16_coords (100k real photo positions),
  resampled to N with a 1-5 km jitter in a random direction. Without ../shared: 3,000 synthetic
  "towns" (uniform on the sphere between 55 S and 70 N, Zipf-distributed sizes) with 1-50 km
  jitter; the numbers then differ (documented fallback, never silently mixed).
- descriptors: clustered unit vectors, one cluster ("place") per base position, so the
  references resampled from one photo position are near-duplicates of each other (nearly tied
  neighbours: a pessimistic case for compressed indexes). Queries are references plus noise,
  with the prior at the reference's position (the prior picks that reference's submap).

For every index kind, in one run: ``vlm-vpr build-map --descriptors`` in a child process (wall
time, peak RSS from wait4), disk size, then a fresh child process that opens the map and
answers queries: start time (process launch to ready), RSS after start and after 1,000 queries
over random submaps (anonymous and file-backed, from /proc/self/status), query latency with
top-50 + re-rank (1 submap, the largest submap, 3 submaps, global; median and p95, warm), and
recall@1 / recall@50 of the retrieval vs exact float32 brute force over the same submap.

Issue 31: per kind, the thread policy and the re-rank are compared in the query process,
interleaved query by query, each query's runs in a random order (wall ms, and CPU ms of the
calling thread): the largest submap's search alone, the paper's query on it and the posterior
over the whole map, with one FAISS thread per query (default), with FAISS's OpenMP default,
and with the re-rank of before (FAISS's fp16 decoder). The 1-submap and largest-submap queries
also run each between two host-speed probes (``cpuinfo.paired``): their medians with the host
at full speed and contended (a shared machine's other tenant slows the same code ~1.6x).

    .venv/bin/python benchmarks/bench_scale.py --n 100000 [--kinds flat,fp16,pq,auto]
        [--ram-budget-mb 250] [--max-submap-size 50000] [--workdir /tmp/bench_scale] [--keep]
        [--reuse] [--cpu-paths native|avx2|generic]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo, scale_policy  # noqa: E402
SHARED = Path(os.environ.get("VLM_VPR_SHARED", REPO.parent / "shared"))
MP16 = SHARED / "data" / "mp16_coords"
CHUNK = 100_000
from vlm_vpr_ros.geodesy import EARTH_RADIUS_KM as EARTH_KM  # noqa: E402 (after sys.path)


# -- data --------------------------------------------------------------------------------------
def base_positions(seed: int) -> tuple[np.ndarray, str]:
    files = sorted(MP16.glob("*.csv")) if MP16.is_dir() else []
    if files:
        rows = []
        for f in files:
            with f.open() as fh:
                for r in csv.DictReader(fh):
                    rows.append((float(r["LAT"]), float(r["LON"])))
        return np.array(rows), f"MP-16 ({len(rows):,} real positions, {MP16})"
    rng = np.random.default_rng(seed)
    k = 3000
    lat = np.degrees(np.arcsin(rng.uniform(np.sin(np.radians(-55)), np.sin(np.radians(70)), k)))
    lon = rng.uniform(-180, 180, k)
    return np.stack([lat, lon], 1), "synthetic towns (../shared absent: fallback)"


def jitter(lat, lon, km, bearing):
    """Destination point at ``km`` along ``bearing`` (radians) from (lat, lon)."""
    p1, l1, d = np.radians(lat), np.radians(lon), km / EARTH_KM
    p2 = np.arcsin(np.sin(p1) * np.cos(d) + np.cos(p1) * np.sin(d) * np.cos(bearing))
    l2 = l1 + np.arctan2(np.sin(bearing) * np.sin(d) * np.cos(p1),
                         np.cos(d) - np.sin(p1) * np.sin(p2))
    return np.degrees(p2), (np.degrees(l2) + 540) % 360 - 180


def make_data(work: Path, n: int, dim: int, n_queries: int, seed: int = 0) -> dict:
    meta_path = work / "data.json"
    if meta_path.exists():
        meta = json.loads(meta_path.read_text())
        if meta.get("n") == n and meta.get("dim") == dim:
            print(f"reusing data in {work}")
            return meta
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    base, src = base_positions(seed)
    rng = np.random.default_rng(seed)
    fallback = "fallback" in src
    if fallback:  # Zipf-like town sizes
        w = 1.0 / np.arange(1, len(base) + 1) ** 0.8
        place = rng.choice(len(base), n, p=w / w.sum())
    else:
        place = rng.integers(0, len(base), n)
    centres = rng.normal(size=(len(base), dim)).astype(np.float32)
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    desc = np.lib.format.open_memmap(work / "desc.npy", "w+", np.float32, (n, dim))
    lo_km, hi_km = (1.0, 50.0) if fallback else (1.0, 5.0)
    with open(work / "coords.csv", "w") as fh:
        fh.write("file,lat,lon\n")
        for s in range(0, n, CHUNK):
            e = min(n, s + CHUNK)
            p = place[s:e]
            g = rng.normal(size=(e - s, dim)).astype(np.float32) / math.sqrt(dim)
            x = centres[p] + 0.7 * g
            x /= np.linalg.norm(x, axis=1, keepdims=True)
            desc[s:e] = x
            la, lo = jitter(base[p, 0], base[p, 1], rng.uniform(lo_km, hi_km, e - s),
                            rng.uniform(0, 2 * np.pi, e - s))
            fh.write("".join(f"r{i},{a:.6f},{b:.6f}\n" for i, a, b in zip(range(s, e), la, lo)))
    desc.flush()
    # queries: a reference + noise; prior = that reference's position
    qrows = np.sort(rng.choice(n, n_queries, replace=False))
    q = np.asarray(desc[qrows]) + 0.25 * rng.normal(size=(n_queries, dim)).astype(
        np.float32) / math.sqrt(dim)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    del desc
    pos = np.empty((n_queries, 2))
    want = {int(r): j for j, r in enumerate(qrows)}
    with open(work / "coords.csv") as fh:
        next(fh)
        for i, line in enumerate(fh):
            j = want.get(i)
            if j is not None:
                _, a, b = line.split(",")
                pos[j] = float(a), float(b)
    np.savez(work / "queries.npz", q=q.astype(np.float32), rows=qrows, pos=pos)
    meta = {"n": n, "dim": dim, "positions": src, "gen_s": round(time.perf_counter() - t0, 1)}
    meta_path.write_text(json.dumps(meta))
    return meta


# -- child processes ---------------------------------------------------------------------------
def run_measured(cmd: list[str]) -> tuple[float, float, str]:
    """(wall s, peak RSS GiB of the child, its stdout). The peak is the child's own VmHWM,
    printed by it at exit: ``ru_maxrss`` from ``wait4`` would include this parent's RSS (Linux
    keeps the pre-exec high-water mark; after writing the data, that is the 8.4 GB file)."""
    wrapped = [sys.executable, "-c", HWM_WRAPPER] + cmd[1:]  # cmd = python -m MODULE ...
    t0 = time.perf_counter()
    p = subprocess.run(wrapped, stdout=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"failed ({p.returncode}): {' '.join(cmd)}")
    hwm = [line for line in p.stdout.splitlines() if line.startswith("VMHWM_KB ")]
    return wall, int(hwm[-1].split()[1]) / 2 ** 20, p.stdout


#: ``python -c HWM_WRAPPER -m MODULE ARGS...`` runs the module, then prints its VmHWM
HWM_WRAPPER = """
import runpy, sys
mod = sys.argv[2]
sys.argv = [mod] + sys.argv[3:]
code = 0
try:
    runpy.run_module(mod, run_name="__main__", alter_sys=True)
except SystemExit as exc:
    code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
with open("/proc/self/status") as fh:
    hwm = [line.split()[1] for line in fh if line.startswith("VmHWM")][0]
print("VMHWM_KB", hwm, flush=True)
sys.exit(code)
"""


def status_mib() -> dict:
    out = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            k, _, v = line.partition(":")
            if k in ("VmRSS", "RssAnon", "RssFile", "VmHWM"):
                out[k] = int(v.split()[0]) / 1024
    return out


def child(map_dir: str, work: str, n_loop: int, n_global: int) -> None:
    """Runs in a fresh process: open, report RSS, time queries, recall vs exact."""
    t_start = time.perf_counter()
    from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
    from vlm_vpr_ros.maps.reference_map import ReferenceMap
    from vlm_vpr_ros.priors.provider import Prior, PriorResult

    m = ReferenceMap.load(map_dir)
    # the paper's search (the one submap of the prior) isolates the per-submap cost; the
    # default posterior fusion searches every submap in the prior's 95 % region
    loc = Localizer(m, LocalizerConfig(top_p=50, fusion="paper"))
    t_ready = time.perf_counter() - t_start
    print("READY", flush=True)
    rss_start = status_mib()
    z = np.load(Path(work) / "queries.npz")
    q, pos = z["q"], z["pos"]
    priors = [PriorResult(Prior(float(a), float(b), "bench"), "bench") for a, b in pos]
    nq = len(q)

    def timed(lc, idx, prior_of):
        ts = []
        for i in idx:
            t = time.perf_counter()
            lc.localize(q[i % nq], prior_of(i))
            ts.append((time.perf_counter() - t) * 1e3)
        return ts

    loop = list(range(n_loop))
    first = timed(loc, loop, lambda i: priors[i % nq])  # includes lazy opens
    rss_after = status_mib()
    warm = timed(loc, loop, lambda i: priors[i % nq])
    big = max(range(len(m.submaps)), key=lambda i: m.submaps[i].count)
    bp = PriorResult(Prior(*m.submaps[big].centroid, "bench"), "bench")
    assert loc.select_submaps(bp.prior)[0] == [big]
    timed(loc, range(20), lambda i: bp)
    largest = timed(loc, range(300), lambda i: bp)
    # the same queries again, each between two host-speed probes (benchmarks/cpuinfo.py)
    host = {name: cpuinfo.by_host_speed(*cpuinfo.paired(run, 300)) for name, run in (
        ("1 submap", lambda i: loc.localize(q[i % nq], priors[i % nq])),
        ("largest submap", lambda i: loc.localize(q[i % nq], bp)))}
    search_largest = []  # retrieval alone: top-50 (+ re-rank for pq), no fusion
    for i in range(320):
        t = time.perf_counter()
        m.search_submaps([big], np.ascontiguousarray(q[i % nq][None, :]), 50)
        search_largest.append((time.perf_counter() - t) * 1e3)
    search_largest = search_largest[20:]
    shapes = scale_policy.thread_policy(m, loc, big, bp, q, min(200, n_loop))
    loc3 = Localizer(m, LocalizerConfig(top_p=50, fusion="paper", n_submaps=3))
    timed(loc3, range(50), lambda i: priors[i % nq])
    three = timed(loc3, range(300), lambda i: priors[i % nq])
    post = Localizer(m, LocalizerConfig(top_p=50))
    region = [len(post.select_submaps(priors[i % nq].prior)[0]) for i in range(100)]
    timed(post, range(20), lambda i: priors[i % nq])
    posterior = timed(post, range(100), lambda i: priors[i % nq])
    timed(loc, range(3), lambda i: None)
    glob = timed(loc, range(n_global), lambda i: None)
    # every submap is open now: the descriptors the process holds (a mapped file keeps none)
    fds = (len(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else -1,
           sum(s.is_open for s in m.submaps))
    # recall vs exact (precomputed by the parent for the 1-submap search)
    ex = np.load(Path(work) / "exact.npz")
    r1 = r50 = 0.0
    for j, i in enumerate(ex["qidx"]):
        chosen, _ = loc.select_submaps(priors[i].prior)
        got = [int(c.ref_id[1:]) for c in loc.search(q[i], chosen, 50)]
        want = ex["top"][j][ex["top"][j] >= 0]
        r1 += got[0] == want[0]
        r50 += len(set(got) & set(want.tolist())) / len(want)
    res = {"open_s": t_ready, "rss_start": rss_start, "rss_after": rss_after, "fds": fds,
           "lat_first": first, "lat_1": warm, "lat_largest": largest,
           "search_largest": search_largest, "lat_3": three, "host": host,
           "lat_posterior": posterior, "region_submaps": statistics.median(region),
           "lat_global": glob, "shapes": shapes,
           "largest": [m.submaps[big].id, m.submaps[big].count, m.submaps[big].kind],
           "recall1": r1 / len(ex["qidx"]), "recall50": r50 / len(ex["qidx"]),
           "n_submaps": len(m.submaps)}
    print("RESULT " + json.dumps(res), flush=True)


def exact_top(map_dir: Path, work: Path, n_recall: int) -> None:
    """Exact float32 top-50 in each recall query's submap, from the source descriptors."""
    from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
    from vlm_vpr_ros.maps.reference_map import ReferenceMap
    from vlm_vpr_ros.priors.provider import Prior

    m = ReferenceMap.load(map_dir)
    loc = Localizer(m, LocalizerConfig(fusion="paper"))
    z = np.load(work / "queries.npz")
    q, pos = z["q"], z["pos"]
    desc = np.load(work / "desc.npy", mmap_mode="r")
    qidx = np.arange(min(n_recall, len(q)))
    by_sub: dict[int, list[int]] = {}
    for i in qidx:
        chosen, _ = loc.select_submaps(Prior(float(pos[i, 0]), float(pos[i, 1]), "b"))
        by_sub.setdefault(chosen[0], []).append(int(i))
    top = np.full((len(qidx), 50), -1, dtype=np.int64)  # -1: submap smaller than 50
    for si, members in by_sub.items():
        sub = m.submaps[si]
        rows = np.fromiter((int(s[1:]) for s in sub.ids), dtype=np.int64, count=sub.count)
        order = np.argsort(rows)
        vecs = np.asarray(desc[rows[order]], dtype=np.float32)
        norms = np.einsum("ij,ij->i", vecs, vecs)
        for i in members:
            d = norms - 2.0 * vecs @ q[i]
            best = np.argsort(d, kind="stable")[:50]
            top[i, :len(best)] = rows[order][best]
        del vecs
    np.savez(work / "exact.npz", qidx=qidx, top=top)


# -- report ------------------------------------------------------------------------------------

def med_p95(ts):
    s = sorted(ts)
    return f"{statistics.median(s):.2f} / {s[int(0.95 * (len(s) - 1))]:.2f}"


def du(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 2 ** 30


def report(results: dict, n: int) -> None:
    kinds = list(results)
    rows = [
        ("build wall time (s)", lambda r: f"{r['build_s']:.0f}"),
        ("build peak RSS (GiB)", lambda r: f"{r['build_rss']:.2f}"),
        ("disk size (GiB)", lambda r: f"{r['disk']:.2f}"),
        ("fresh-process start (s)", lambda r: f"{r['start_s']:.2f}"),
        ("  of which open map (s)", lambda r: f"{r['open_s']:.2f}"),
        ("RSS anon after start (MiB)", lambda r: f"{r['rss_start']['RssAnon']:.0f}"),
        ("RSS anon after 1k queries (MiB)", lambda r: f"{r['rss_after']['RssAnon']:.0f}"),
        ("RSS file after 1k queries (MiB)", lambda r: f"{r['rss_after']['RssFile']:.0f}"),
        ("open descriptors, all submaps opened", lambda r: "{} ({} open)".format(
            *r["fds"]) if r.get("fds") else "n/a"),
        ("1k queries, first pass (ms med/p95)", lambda r: med_p95(r["lat_first"])),
        ("1 submap (ms med/p95)", lambda r: med_p95(r["lat_1"])),
        ("largest submap, search only (ms med/p95)", lambda r: med_p95(r["search_largest"])),
        ("largest submap (ms med/p95)", lambda r: med_p95(r["lat_largest"])),
        ("3 submaps (ms med/p95)", lambda r: med_p95(r["lat_3"])),
        ("prior region, posterior (ms med/p95)", lambda r: med_p95(r["lat_posterior"])),
        ("  submaps in the region (median)", lambda r: f"{r['region_submaps']:.0f}"),
        ("global (ms med/p95)", lambda r: med_p95(r["lat_global"])),
        ("recall@1 vs exact (%)", lambda r: f"{100 * r['recall1']:.2f}"),
        ("recall@50 vs exact (%)", lambda r: f"{100 * r['recall50']:.2f}"),
    ]
    r0 = results[kinds[0]]
    print(f"\n{n:,} references, {r0['n_submaps']} submaps; largest {r0['largest'][0]} "
          f"({r0['largest'][1]:,} refs); latency = localize() top-50 + re-rank, warm, paper "
          f"fusion unless noted")
    print(f"{'':44}" + "".join(f"{k:>18}" for k in kinds))
    for name, fn in rows:
        print(f"{name:44}" + "".join(f"{fn(results[k]):>18}" for k in kinds))
    print("host speed: the 1-submap and largest-submap queries again, each between two probes "
          "(benchmarks/cpuinfo.py)")
    fastest = min(split["probe_p5"] for r in results.values() for split in r["host"].values())
    for kind, r in results.items():
        for name, split in r["host"].items():
            print("  " + cpuinfo.host_speed_row(f"{kind}, {name}", split, fastest))
    for kind, r in results.items():
        if r.get("shapes"):
            scale_policy.print_table(kind, r)
    med = statistics.median
    for base in ("flat", "fp16"):
        if "pq" in results and base in results:
            b, p = results[base], results["pq"]
            print(f"pq / {base} (same run): disk {p['disk'] / b['disk']:.2f}x, RSS anon after "
                  f"1k queries {p['rss_after']['RssAnon'] / b['rss_after']['RssAnon']:.2f}x, "
                  f"largest-submap search "
                  f"{med(p['search_largest']) / med(b['search_largest']):.2f}x, "
                  f"global {med(p['lat_global']) / med(b['lat_global']):.2f}x")


def build(a: argparse.Namespace, cli: list[str], work: Path, out: Path, kind: str,
          cap: int) -> tuple[float, float]:
    """A fresh build of one kind in a child process: (wall s, peak RSS GiB)."""
    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(work / f".map_{kind}.partial", ignore_errors=True)  # a fresh build
    build_s, build_rss, _ = run_measured(
        cli + ["-q", "build-map", "--descriptors", str(work / "desc.npy"),
               "--coords", str(work / "coords.csv"), "--descriptor", "cosplace",
               "--out", str(out), "--index", kind, "--clusters", str(a.clusters),
               "--max-submap-size", str(cap), "--rerank-factor", str(a.rerank_factor)]
        + (["--ram-budget-mb", f"{a.ram_budget_mb:g}"] if a.ram_budget_mb else []))
    return build_s, build_rss


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--dim", type=int, default=512)
    ap.add_argument("--kinds", default="flat,fp16,pq")
    ap.add_argument("--clusters", type=int, default=100)
    ap.add_argument("--max-submap-size", type=int, default=None,
                    help="balance: split submaps above this size (default max(20000, n/80))")
    ap.add_argument("--rerank-factor", type=int, default=16)
    ap.add_argument("--ram-budget-mb", type=float, default=None,
                    help="for --kinds auto: the build's RAM budget (e.g. 250)")
    ap.add_argument("--queries", type=int, default=1000)
    ap.add_argument("--global-queries", type=int, default=30)
    ap.add_argument("--recall-queries", type=int, default=300)
    ap.add_argument("--workdir", default="/tmp/bench_scale")
    ap.add_argument("--keep", action="store_true", help="keep data and maps afterwards")
    ap.add_argument("--reuse", action="store_true",
                    help="query an existing map of the workdir (--keep of an earlier run) "
                         "instead of building it again")
    ap.add_argument("--child", nargs=2, metavar=("MAP", "WORK"), help=argparse.SUPPRESS)
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    a = ap.parse_args()
    if not a.child:
        print(cpuinfo.cpu_line(), flush=True)
    if a.child:
        child(a.child[0], a.child[1], a.queries, a.global_queries)
        return 0
    work = Path(a.workdir) / f"n{a.n}"
    cap = a.max_submap_size or max(20_000, a.n // 80)
    meta = make_data(work, a.n, a.dim, max(a.queries, a.recall_queries))
    print(f"{a.n:,} x {a.dim}-D references at {meta['positions']}; data made in "
          f"{meta['gen_s']} s; K={a.clusters}, max submap size {cap:,}; rerank factor "
          f"{a.rerank_factor}; machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    cli = [sys.executable, "-m", "vlm_vpr_ros.cli"]
    results = {}
    if not a.reuse:
        (work / "exact.npz").unlink(missing_ok=True)  # depends on this run's partition
    for kind in a.kinds.split(","):
        out = work / f"map_{kind}"
        if a.reuse and (out / "manifest.json").is_file():
            build_s, build_rss = math.nan, math.nan  # built by an earlier run
        else:
            build_s, build_rss = build(a, cli, work, out, kind, cap)
        if not (work / "exact.npz").exists():
            exact_top(out, work, a.recall_queries)
        t0 = time.perf_counter()
        p = subprocess.Popen([sys.executable, __file__, "--child", str(out), str(work),
                              "--queries", str(a.queries), "--global-queries",
                              str(a.global_queries)], stdout=subprocess.PIPE, text=True)
        start_s = None
        res = None
        for line in p.stdout:
            if line.startswith("READY") and start_s is None:
                start_s = time.perf_counter() - t0
            elif line.startswith("RESULT "):
                res = json.loads(line[7:])
        if p.wait() != 0 or res is None:
            raise SystemExit(f"query child failed for {kind}")
        res.update(build_s=build_s, build_rss=build_rss, disk=du(out), start_s=start_s)
        results[kind] = res
        print(f"  {kind}: built in {build_s:.0f} s (peak {build_rss:.2f} GiB), "
              f"{res['disk']:.2f} GiB on disk, start {start_s:.2f} s", flush=True)
        (work / "results.json").write_text(json.dumps(results))
        report(results, a.n)  # after every kind: a long run shows what it has
        if not a.keep and kind != a.kinds.split(",")[-1]:
            shutil.rmtree(out)
    if not a.keep:
        shutil.rmtree(work)
    return 0


if __name__ == "__main__":
    sys.exit(main())
