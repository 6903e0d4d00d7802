"""``vlm-vpr demo``: the whole method on the shipped OpenStreetView-5M images, in about a minute.

1. A map of the 71 images (one submap per country) and 71 queries that are altered copies of
   them (the place *is* in the map: the easy case for VPR, so VPR alone is right everywhere and
   a prior can only cost fixes — the table shows how much each fusion gives away).
2. The look-alike step (:mod:`.lookalike`): the same queries on a map where every place has a
   look-alike 5,000 km away, built from the shipped images and said so in the output. VPR
   alone picks the wrong twin about half the time; the real OSV-5M predictions as priors fix
   most of them.
3. A rosbag2 bag of the queries, evaluated offline (``vlm-vpr evaluate-bag``).

Every table is printed and written to ``OUT/demo.json`` (the docs' tables are generated from it
by ``scripts/gen_docs.py``), with an error CDF and a contact sheet of the look-alike step. The
demo is deterministic: the same numbers on every run and machine.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import cv2
import numpy as np

from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.geodesy import THRESHOLDS_KM

log = logging.getLogger(__name__)

DEMO_DATA = Path(__file__).resolve().parents[1] / "data" / "osv5m_demo"
#: the demo's tables add street level (25 m) to the paper's thresholds
THRESHOLDS = (0.025, *THRESHOLDS_KM)
JSON_FORMAT = "vlm_vpr_ros.demo"
VPR, PRIOR, PAPER, PAPER_NO_RR = ("VPR only (no prior)", "prior only (OSV-5M model)",
                                  "paper: country submap+re-rank",
                                  "paper: country submap, no re-rank")
PAPER_NO_SUB, FUSED = "paper: re-rank, no submap", "prior+VPR (default fusion)"
TITLES = {
    "map": "Demo: 71 OSV-5M street images (48 countries); queries are altered copies of map "
           "images",
    "lookalike": "Look-alike step: the same queries on a map where every place has a "
                 "look-alike 5000 km away (built from the shipped images)",
    "bag": "Demo bag evaluated offline (vlm-vpr evaluate-bag)",
}


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


def run_step(ref_map, runs: dict, files: list[str], qdesc: np.ndarray, queries_csv: Path,
             out: Path) -> tuple[dict, dict]:
    """Localize the described queries once per run (``name -> LocalizerConfig``, with the
    recorded OSV-5M priors unless the name says "no prior"; ``None``: the prior itself as the
    estimate). Writes ``out/<n>.csv``; returns (summaries, per-run errors/coverage)."""
    from vlm_vpr_ros.evaluation.metrics import evaluate_results_csv
    from vlm_vpr_ros.files.csvio import write_csv_atomic
    from vlm_vpr_ros.localization.batch import RESULT_FIELDS
    from vlm_vpr_ros.localization.localizer import Localizer
    from vlm_vpr_ros.localization.query_descriptors import localize_descriptors
    from vlm_vpr_ros.priors import create_prior_provider
    from vlm_vpr_ros.priors.simple import read_prior_csv

    priors_csv = DEMO_DATA / "priors_osv5m_baseline.csv"
    summaries, extras = {}, {}
    for i, (name, config) in enumerate(runs.items()):
        res = out / f"results_{i}.csv"
        if config is None:
            pri = read_prior_csv(priors_csv)
            write_csv_atomic(res, ["file", "lat", "lon"],
                             [{"file": f, "lat": pri[f][0], "lon": pri[f][1]} for f in files])
        else:
            provider = (create_prior_provider("none") if "no prior" in name else
                        create_prior_provider("recorded", {"path": str(priors_csv)}))
            try:
                rows = list(localize_descriptors(Localizer(ref_map, config), provider, files,
                                                 qdesc))
            finally:
                provider.close()
            write_csv_atomic(res, RESULT_FIELDS, rows)
        summaries[name], extras[name] = evaluate_results_csv(res, queries_csv, THRESHOLDS)
        extras[name]["results_csv"] = str(res)
    return summaries, extras


def run_demo(out: str | Path, with_bag: bool = True) -> int:
    from vlm_vpr_ros.evaluation.lookalike import build_lookalike_map, write_refs
    from vlm_vpr_ros.evaluation.metrics import format_table
    from vlm_vpr_ros.files.atomic import atomic_save_npy
    from vlm_vpr_ros.files.csvio import read_file_column
    from vlm_vpr_ros.localization.localizer import LocalizerConfig
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.maps.build_images import build_map, read_coords_csv

    out = Path(out)
    t0 = time.monotonic()
    n_steps = 5 if with_bag else 4
    print(f"[1/{n_steps}] building the demo map from {DEMO_DATA / 'images'} (71 images, "
          "country submaps) ...", flush=True)
    map_dir = out / "map"
    build_map(DEMO_DATA / "images", DEMO_DATA / "coords.csv", map_dir, partition="country",
              overwrite=True, progress=False)
    print(f"[2/{n_steps}] writing 71 query images (new crops, light, blur, noise, JPEG) and "
          "describing them ...", flush=True)
    queries = make_queries(out)
    files = read_file_column(queries)
    pipe = LocalizationPipeline.open(map_dir)
    qdesc = np.stack([pipe.describe(load_image(out / "queries" / f)) for f in files])
    atomic_save_npy(out / "queries_descriptors.npy", qdesc)  # rows of queries.csv
    paper = LocalizerConfig(fusion="paper")
    print(f"[3/{n_steps}] localizing the queries on the demo map ...", flush=True)
    runs = {VPR: paper, PRIOR: None, PAPER_NO_RR: LocalizerConfig(fusion="paper", rerank=False),
            PAPER: paper, PAPER_NO_SUB: LocalizerConfig(fusion="paper", use_submaps=False),
            FUSED: LocalizerConfig(fusion="posterior")}
    (out / "results").mkdir(parents=True, exist_ok=True)
    tables, extras = {}, {}
    tables["map"], extras["map"] = run_step(pipe.map, runs, files, qdesc, queries,
                                            out / "results")
    print("\n" + format_table(tables["map"], title=TITLES["map"]) + "\n", flush=True)
    print(f"[4/{n_steps}] the look-alike step: 4 mild copies of every shipped image, 2 at its "
          "place and 2 at a look-alike place 5000 km away (284 references) ...", flush=True)
    look = out / "lookalike"
    refs = write_refs(DEMO_DATA / "images", read_coords_csv(DEMO_DATA / "coords.csv"), look)
    look_map = build_lookalike_map(pipe, refs, look / "refs", look / "map")
    (look / "results").mkdir(parents=True, exist_ok=True)
    tables["lookalike"], extras["lookalike"] = run_step(
        look_map, {VPR: paper, PRIOR: None, PAPER: paper, FUSED: LocalizerConfig()}, files,
        qdesc, queries, look / "results")
    print("\n" + format_table(tables["lookalike"], title=TITLES["lookalike"]))
    gain = tables["lookalike"][FUSED]["accuracy"]["0.025km"] - \
        tables["lookalike"][VPR]["accuracy"]["0.025km"]
    print(f"      at 25 m the prior turns {gain:+.1f} points of wrong look-alikes into fixes\n")
    figures = _figures(out, files, extras["lookalike"])
    if with_bag:
        tables["bag"], bag_outputs = _bag_demo(out, map_dir, queries, n_steps)
        figures.update(bag_outputs)
    _write_json(out, tables, extras, figures, time.monotonic() - t0)
    print(f"done in {time.monotonic() - t0:.0f} s; tables in {out / 'demo.json'}, outputs in "
          f"{out}/")
    return 0


def _figures(out: Path, files: list[str], extras: dict) -> dict:
    from vlm_vpr_ros.evaluation.lookalike import contact_sheet
    from vlm_vpr_ros.evaluation.plots import plot_error_cdf

    errs = {name: e["errors_km"] for name, e in extras.items()}
    cdf = plot_error_cdf(out / "lookalike" / "error_cdf.png", errs, thresholds_km=THRESHOLDS,
                         title="Look-alike step: error CDF (71 queries)")
    sheet = contact_sheet(out, files, extras[VPR], extras[FUSED], extras[PRIOR],
                          out / "lookalike" / "contact_sheet.png")
    print(f"      error CDF: {cdf}\n      contact sheet: {sheet}\n", flush=True)
    return {"lookalike_error_cdf_png": str(cdf), "lookalike_contact_sheet_png": str(sheet)}


def _bag_demo(out: Path, map_dir: Path, queries: Path, n_steps: int) -> tuple[dict, dict]:
    from vlm_vpr_ros.bags.demo import run_bag_demo
    from vlm_vpr_ros.evaluation.metrics import format_table

    print(f"[{n_steps}/{n_steps}] making a demo bag from the queries and evaluating it ...",
          flush=True)
    info = run_bag_demo(out / "bag_demo", map_dir, out / "queries", queries,
                        DEMO_DATA / "priors_osv5m_baseline.csv", thresholds_km=THRESHOLDS)
    table = {"bag, " + FUSED: info.pop("summary")}
    print(format_table(table, title=TITLES["bag"]))
    for key, value in info.items():
        print(f"      {key}: {value}")
    return table, {k: v for k, v in info.items() if k.endswith("_png")}


def _write_json(out: Path, tables: dict, extras: dict, figures: dict, elapsed: float) -> None:
    from vlm_vpr_ros.evaluation.metrics import table_cells
    from vlm_vpr_ros.files.atomic import atomic_write_json

    doc = {"format": JSON_FORMAT, "version": 1,
           "tables": {}, "summaries": tables,
           "coverage": {step: {name: {"68": e["coverage_pct"], "95": e["coverage95_pct"]}
                               for name, e in ex.items()} for step, ex in extras.items()},
           "figures": figures, "elapsed_s": round(elapsed, 1)}
    for step, rows in tables.items():
        head, body = table_cells(rows)
        doc["tables"][step] = {"title": TITLES[step], "columns": head, "rows": body}
    atomic_write_json(out / "demo.json", doc)
