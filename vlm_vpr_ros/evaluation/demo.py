"""``vlm-vpr demo``: the whole method on the shipped OpenStreetView-5M images.

What it shows: map building, submaps, prior-guided retrieval and re-ranking, evaluation, on real
street-level images from 48 countries, offline. What it does not show: planet-scale accuracy —
every query is a re-cropped, re-lit, re-compressed copy of a map image (the place *is* in the
map, the best case for VPR), and the map has only 71 references.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import cv2
import numpy as np

from vlm_vpr_ros.files.images import load_image

log = logging.getLogger(__name__)

DEMO_DATA = Path(__file__).resolve().parents[1] / "data" / "osv5m_demo"


def make_query(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A different view of the same frame: random crop (60-80 % of each side), resize to
    640x480, brightness/contrast/gamma change, blur and sensor noise."""
    h, w = image.shape[:2]
    sh, sw = rng.uniform(0.6, 0.8), rng.uniform(0.6, 0.8)
    ch, cw = int(h * sh), int(w * sw)
    y0, x0 = rng.integers(0, h - ch + 1), rng.integers(0, w - cw + 1)
    crop = cv2.resize(image[y0:y0 + ch, x0:x0 + cw], (640, 480), interpolation=cv2.INTER_LINEAR)
    x = crop.astype(np.float32) / 255.0
    x = np.clip(x * rng.uniform(0.7, 1.2) + rng.uniform(-0.08, 0.08), 0, 1)
    x = x ** rng.uniform(0.8, 1.25)
    x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.3, 1.0))
    x = x + rng.normal(0.0, 0.01, x.shape).astype(np.float32)
    return (np.clip(x, 0, 1) * 255).round().astype(np.uint8)


def make_queries(out_dir: Path, seed: int = 0) -> Path:
    """Write query images + ``queries.csv`` (file, lat, lon ground truth); returns the CSV."""
    from vlm_vpr_ros.files.csvio import write_csv_atomic
    from vlm_vpr_ros.maps.build_images import read_coords_csv

    qdir = out_dir / "queries"
    qdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for i, (f, lat, lon) in enumerate(read_coords_csv(DEMO_DATA / "coords.csv")):
        rng = np.random.default_rng([seed, i])
        q = make_query(load_image(DEMO_DATA / "images" / f), rng)
        cv2.imwrite(str(qdir / f), cv2.cvtColor(q, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, 85])
        rows.append({"file": f, "lat": lat, "lon": lon})
    csv_path = out_dir / "queries.csv"
    write_csv_atomic(csv_path, ["file", "lat", "lon"], rows)
    return csv_path


def run_demo(out: str | Path, with_bag: bool = True) -> int:
    from vlm_vpr_ros.localization.batch import RESULT_FIELDS, localize_files
    from vlm_vpr_ros.files.csvio import write_csv_atomic
    from vlm_vpr_ros.evaluation.metrics import evaluate_results_csv, format_table
    from vlm_vpr_ros.localization.localizer import LocalizerConfig
    from vlm_vpr_ros.maps.build_images import build_map
    from vlm_vpr_ros.files.csvio import read_file_column
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.priors import create_prior_provider

    out = Path(out)
    t0 = time.monotonic()
    print(f"[1/4] building the demo map from {DEMO_DATA / 'images'} (71 images, country "
          "submaps) ...", flush=True)
    map_dir = out / "map"
    build_map(DEMO_DATA / "images", DEMO_DATA / "coords.csv", map_dir, partition="country",
              overwrite=True)
    print("[2/4] writing 71 query images (new crops, light, blur, noise, JPEG) ...", flush=True)
    queries = make_queries(out)
    files = read_file_column(queries)
    priors_csv = DEMO_DATA / "priors_osv5m_baseline.csv"
    recorded = ("recorded", {"path": str(priors_csv)})
    runs = {
        "VPR only (no prior)": ("none", {}, LocalizerConfig(fusion="paper")),
        "prior only (OSV-5M model)": None,
        "paper: country submap, no re-rank": (*recorded, LocalizerConfig(fusion="paper",
                                                                         rerank=False)),
        "paper: country submap+re-rank": (*recorded, LocalizerConfig(fusion="paper")),
        "paper: re-rank, no submap": (*recorded, LocalizerConfig(fusion="paper",
                                                                 use_submaps=False)),
        "posterior (default): prior+VPR": (*recorded, LocalizerConfig(fusion="posterior")),
    }
    print("[3/4] localizing the queries ...", flush=True)
    table, coverage = {}, {}
    for i, (name, spec) in enumerate(runs.items()):
        res = out / f"results_{i}.csv"
        if spec is None:  # the prior itself as the estimate
            from vlm_vpr_ros.priors.simple import read_prior_csv

            pri = read_prior_csv(priors_csv)
            write_csv_atomic(res, ["file", "lat", "lon"],
                             [{"file": f, "lat": pri[f][0], "lon": pri[f][1]} for f in files])
        else:
            provider = create_prior_provider(spec[0], spec[1])
            pipe = LocalizationPipeline.open(map_dir, localizer=spec[2])
            write_csv_atomic(res, RESULT_FIELDS,
                             localize_files(pipe, provider, out / "queries", files))
        table[name], extra = evaluate_results_csv(res, queries)
        coverage[name] = (extra["coverage_pct"], extra["coverage95_pct"] or 0.0)
        print(f"      {name}: {res}", flush=True)
    print()
    print(format_table(table, title="Demo: 71 OSV-5M street images (48 countries); "
                                    "queries are altered copies of map images"))
    print(f"      coverage of the posterior's 68 % / 95 % radii: "
          f"{coverage['posterior (default): prior+VPR'][0]:.1f}% / "
          f"{coverage['posterior (default): prior+VPR'][1]:.1f}% "
          "(docs/fusion.md; this map has one image per place, so no leave-one-out calibration)")
    print()
    if with_bag:
        _bag_demo(out, map_dir, queries, priors_csv)
    print(f"done in {time.monotonic() - t0:.0f} s; outputs in {out}/")
    return 0


def _bag_demo(out: Path, map_dir: Path, queries: Path, priors_csv: Path) -> None:
    try:
        from vlm_vpr_ros.bags.demo import run_bag_demo
    except ModuleNotFoundError as exc:
        log.warning("bag demo unavailable (%s)", exc)
        return
    print("[4/4] making a demo bag from the queries and evaluating it ...", flush=True)
    from vlm_vpr_ros.evaluation.metrics import format_table

    info = run_bag_demo(out / "bag_demo", map_dir, out / "queries", queries, priors_csv)
    print(format_table({"bag, posterior fusion (default)": info["summary"]},
                       title="Demo bag evaluated offline (vlm-vpr evaluate-bag)"))
    for key, value in info.items():
        if key != "summary":
            print(f"      {key}: {value}")
