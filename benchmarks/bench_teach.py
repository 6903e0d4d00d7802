"""How accuracy changes when a map grows: SF night (../shared/data/sf_night) built at once vs
first half built + second half added (``vlm-vpr map add``), from the folder and from teach bags.

    .venv/bin/python benchmarks/bench_teach.py [--descriptor vlad_rootsift] [--clusters 10]

Prints one table (R@1 / R@5 within 25 m over the 34 night queries, without a prior and with the
query's true position as the prior — which checks that added references landed in the right
submap), the build/add times measured in this run, and how many queries a grown map answers
exactly like the one-shot map built with the same descriptor state.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))
from benchmarks import cpuinfo  # noqa: E402

from teach_bags import Place, write_teach_bag  # noqa: E402
from vlm_vpr_ros.geodesy import haversine_km  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.localization.localizer import Localizer  # noqa: E402
from vlm_vpr_ros.mapping.assemble import assemble_map
from vlm_vpr_ros.mapping.build_images import build_map  # noqa: E402
from vlm_vpr_ros.mapping.coords_csv import read_coords_csv  # noqa: E402
from vlm_vpr_ros.mapping.edit import add_references  # noqa: E402
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline  # noqa: E402
from vlm_vpr_ros.priors.provider import Prior, PriorResult  # noqa: E402


def _csv(path: Path, rows) -> Path:
    path.write_text("file,lat,lon\n" + "".join(f"{f},{a!r},{b!r}\n" for f, a, b in rows))
    return path


def evaluate(pipe: LocalizationPipeline, qdesc, queries) -> dict:
    out = {}
    for mode in ("no prior", "true prior"):
        r1 = r5 = 0
        answers = []
        for d, (_, lat, lon) in zip(qdesc, queries):
            pr = PriorResult(Prior(lat, lon, "truth"), "truth") if mode == "true prior" else None
            h = pipe.localize_descriptor(d, pr)
            dm = [haversine_km(lat, lon, c.lat, c.lon) * 1000 for c in h.candidates[:5]]
            r1 += dm[0] <= 25
            r5 += min(dm) <= 25
            answers.append(h.ref_id)
        out[mode] = (r1, r5, answers)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", default=str(REPO.parent / "shared"), metavar="DIR")
    ap.add_argument("--descriptor", default="vlad_rootsift")
    ap.add_argument("--clusters", type=int, default=10)
    ap.add_argument("--keep", default=None, metavar="DIR", help="keep the maps here")
    ap.add_argument("--limit", type=int, default=None, metavar="N",
                    help="only the first N database images (smoke test)")
    ap.add_argument("--descriptor-option", action="append", default=[], metavar="KEY=VALUE")
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    print(cpuinfo.cpu_line(), flush=True)
    root = Path(args.shared) / "data" / "sf_night"
    if not root.is_dir():
        print(f"{root} not found: this benchmark needs ../shared", file=sys.stderr)
        return 2
    rows = read_coords_csv(root / "database.csv")[:args.limit]
    queries = read_coords_csv(root / "queries.csv")
    h = len(rows) // 2
    work = Path(args.keep or tempfile.mkdtemp(prefix="bench_teach_"))
    work.mkdir(parents=True, exist_ok=True)
    from vlm_vpr_ros.config import parse_kv

    opts = dict(descriptor=args.descriptor, clusters=args.clusters, progress=False,
                descriptor_config=parse_kv(args.descriptor_option))
    res, times = {}, {}

    t = time.monotonic()
    build_map(root, _csv(work / "all.csv", rows), work / "once", overwrite=True, **opts)
    times["build all at once"] = time.monotonic() - t
    t = time.monotonic()
    build_map(root, _csv(work / "h1.csv", rows[:h]), work / "half", overwrite=True, **opts)
    times["build first half"] = time.monotonic() - t
    shutil.rmtree(work / "grown", ignore_errors=True)
    shutil.copytree(work / "half", work / "grown")
    t = time.monotonic()
    add_references(work / "grown", root, rows[h:], progress=False)
    times["add second half"] = time.monotonic() - t

    # teach bags: the whole database in one drive; first half driven and built, second half
    # driven and added
    for name, part, t0 in (("drive_all", rows, 1_700_200_000),
                           ("drive1", rows[:h], 1_700_000_000),
                           ("drive2", rows[h:], 1_700_100_000)):
        places = [Place((root / f).read_bytes(), a, b) for f, a, b in part]
        shutil.rmtree(work / name, ignore_errors=True)
        write_teach_bag(work / name, places, gaps=(10,), standstill=20, t0=t0 * 10**9)
    from vlm_vpr_ros.bags.teach import build_map_from_bag, extract_references

    t = time.monotonic()
    build_map_from_bag(work / "drive_all", work / "teach_all", overwrite=True, **opts)
    times["build-map --bag drive_all"] = time.monotonic() - t
    t = time.monotonic()
    build_map_from_bag(work / "drive1", work / "teach", overwrite=True, **opts)
    times["build-map --bag drive1"] = time.monotonic() - t
    t = time.monotonic()
    stage = work / "stage2"
    shutil.rmtree(stage, ignore_errors=True)
    tr = extract_references(work / "drive2", stage, progress=False)
    add_references(work / "teach", stage, [(r.id, r.lat, r.lon) for r in tr.references],
                   store_images=True, move_images=True, progress=False)
    times["map add --bag drive2"] = time.monotonic() - t

    half = LocalizationPipeline.open(work / "half")
    once = LocalizationPipeline.open(work / "once")
    grown = LocalizationPipeline.open(work / "grown")
    teach = LocalizationPipeline.open(work / "teach")
    teach_all = LocalizationPipeline.open(work / "teach_all")
    qimg = [load_image(root / f) for f, _, _ in queries]
    qd_half = [half.describe(im) for im in qimg]  # the first half's descriptor state
    qd_once = [once.describe(im) for im in qimg]
    qd_teach = [teach.describe(im) for im in qimg]
    qd_teach_all = [teach_all.describe(im) for im in qimg]
    # one-shot map of all references with the first half's descriptor state (the reference a
    # grown map must equal)
    feats = half.descriptor.describe([load_image(root / f) for f, _, _ in rows])
    same = assemble_map(feats, np.array([[a, b] for _, a, b in rows]), [f for f, _, _ in rows],
                        dict(half.map.descriptor_identity), half.map.descriptor_state,
                        "kmeans", args.clusters)
    same_pipe = LocalizationPipeline(same, half.descriptor, Localizer(same))
    res["first half only"] = (half.map, evaluate(half, qd_half, queries))
    res["all at once (state fitted on all)"] = (once.map, evaluate(once, qd_once, queries))
    res["teach bag, one drive of all places"] = (teach_all.map,
                                                 evaluate(teach_all, qd_teach_all, queries))
    res["all at once (first half's state)"] = (same, evaluate(same_pipe, qd_half, queries))
    res["first half + map add second half"] = (grown.map, evaluate(grown, qd_half, queries))
    res["teach bag drive1 + map add --bag drive2"] = (teach.map,
                                                      evaluate(teach, qd_teach, queries))
    n = len(queries)
    print(f"SF night, {len(rows)} database / {n} queries, descriptor {args.descriptor}, "
          f"kmeans K={args.clusters}")
    print(f"{'map':<42}{'refs':>6}{'submaps':>9}  {'R@1/R@5 no prior':>18}  "
          f"{'R@1/R@5 true prior':>19}")
    for name, (m, ev) in res.items():
        a, b = ev["no prior"][:2], ev["true prior"][:2]
        print(f"{name:<42}{m.n_references:>6}{len(m.submaps):>9}  "
              f"{100 * a[0] / n:>8.1f}/{100 * a[1] / n:<8.1f}  {100 * b[0] / n:>9.1f}/"
              f"{100 * b[1] / n:<8.1f}")
    ga = res["first half + map add second half"][1]
    sa = res["all at once (first half's state)"][1]
    for mode in ("no prior", "true prior"):
        eq = sum(x == y for x, y in zip(ga[mode][2], sa[mode][2]))
        print(f"grown vs one-shot with the same state, {mode}: {eq}/{n} identical answers")
    for k, v in times.items():
        print(f"time {k:<28}{v:7.1f} s")
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
