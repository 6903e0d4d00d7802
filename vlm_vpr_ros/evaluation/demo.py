"""``vlm-vpr demo``: the whole method on the shipped OpenStreetView-5M images (README: time).

1. A map of the 71 images (one submap per country) and 71 queries that are altered copies of
   them (the place *is* in the map: the easy case for VPR, so VPR alone is right everywhere and
   a prior can only cost fixes — the table shows how much each fusion gives away).
2. The look-alike step (:mod:`.lookalike`): the same queries on a map where every place has a
   look-alike 5,000 km away with the very same image, built from the shipped images and said so
   in the output. VPR alone cannot tell the twins apart (an exact tie, broken by the map's
   order: the wrong twin for about half the places); the real OSV-5M predictions as priors fix
   most of them.
3. A rosbag2 bag of the queries, evaluated offline (``vlm-vpr evaluate-bag``).

The default pipeline's rows (the default fusion, and the bag) are *verified* as the node and
``localize`` verify them (docs/verification.md): the fix columns say how many answers would be
published as ``STATUS_FIX`` and how many of those are right. The retrieval baselines (VPR only,
the paper's modes) and the prior alone are not verified (``-``). The query's local features
come from the descriptor's own SIFT pass (:meth:`LocalizationPipeline.describe_query`), as in
the node.

Every table is printed and written to ``OUT/demo.json`` (the docs' tables are generated from it
by ``scripts/gen_docs.py``), with an error CDF and a contact sheet of the look-alike step. The
demo is deterministic: the same numbers on every run, and every table row rests on facts that
floating point does not move (a true match against non-matches, distances to the prior, exact
ties broken by a stated rule), so the same tables on every CPU; ``scripts/check_cpu_paths.py``
runs it under forced SIMD/BLAS/thread settings and compares. The paper's modes that pick among
references that match nothing by descriptor distance are not shown: on this 71-image map the
whitened descriptors put every non-matching pair at nearly the same distance, so that pick is
floating-point noise (``paper: re-rank, no submap``: which 50 of 71 make the top-50;
``paper: country submap, no re-rank``: the nearest reference of a submap without the place).

When standard output is not a terminal (a log file, CI) a long step prints a plain progress line
every :data:`HEARTBEAT_S` seconds; the last line gives the wall and CPU time.
"""

from __future__ import annotations

import contextlib
import csv
import logging
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.evaluation.lookalike import LOOKALIKE_KM
from vlm_vpr_ros.geodesy import THRESHOLDS_KM
from vlm_vpr_ros.localization.verification.status import StatusPolicy

log = logging.getLogger(__name__)

DEMO_DATA = Path(__file__).resolve().parents[1] / "data" / "osv5m_demo"
#: the demo's tables add street level (25 m) to the paper's thresholds
THRESHOLDS = (0.025, *THRESHOLDS_KM)
JSON_FORMAT = "vlm_vpr_ros.demo"
VPR, PRIOR, PAPER = ("VPR only (no prior)", "prior only (OSV-5M model)",
                     "paper: country submap+re-rank")
FUSED = "prior+VPR (default fusion)"
TRUSTED = "prior+VPR, trust_prior_for_fix"
#: seconds between two progress lines of a long step when stdout is not a terminal
HEARTBEAT_S = 30.0


def _shipped_places() -> tuple[int, int]:
    """(images, countries) of the shipped demo data, from its coords.csv."""
    with open(DEMO_DATA / "coords.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    return len(rows), len({r["country"] for r in rows})


_N_IMAGES, _N_COUNTRIES = _shipped_places()
TITLES = {
    "map": f"Demo: {_N_IMAGES} OSV-5M street images ({_N_COUNTRIES} countries); queries are "
           "altered copies of map images",
    "lookalike": "Look-alike step: the same queries on a map where every place has a "
                 f"look-alike {LOOKALIKE_KM:g} km away (built from the shipped images)",
    "bag": "Demo bag evaluated offline (vlm-vpr evaluate-bag)",
    "fixes": "Verified fixes: the default pipeline's answers published as STATUS_FIX",  # printed
}
#: the rows of the fixes table: (step, label) of the steps' verified runs
FIX_STEPS = (("map", "demo map"), ("lookalike", "look-alike map"))
FIX_TABLE_COLUMNS = ("", "n", "25m", "fixes", "fix prec 25m", "fix prec 50m")


@dataclass(frozen=True)
class Run:
    """One row of a demo table: a localizer configuration (None: the recorded prior itself is
    the estimate), with or without the recorded OSV-5M priors, verified or not, and the status
    rule of its fixes."""

    config: object = None  # LocalizerConfig | None
    prior: bool = True
    verify: bool = False
    status: StatusPolicy = field(default_factory=StatusPolicy)


FIX_MEANING = (
    "      fixes: the share of answers published as STATUS_FIX: verified (local features + "
    "geometry\n      over the top 20 candidates), p_correct >= 0.99, protection level < 50 m "
    "and sigma <= 50 m\n      (docs/verification.md);\n      fix prec 25m / 50m: the share of "
    "those fixes within 25 m / 50 m of the truth; '-': not verified")


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


@contextlib.contextmanager
def progress_lines(label: str, every_s: float = HEARTBEAT_S):
    """While the block runs, print ``label: N s`` every ``every_s`` seconds if stdout is not a
    terminal (a terminal shows the steps' own progress bars)."""
    out = sys.stdout
    if out.isatty():
        yield
        return
    done, t0 = threading.Event(), time.monotonic()

    def beat() -> None:
        while not done.wait(every_s):
            print(f"      ... {label}: {time.monotonic() - t0:.0f} s", file=out, flush=True)

    thread = threading.Thread(target=beat, name="demo-progress", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def make_queries(out_dir: Path, seed: int = 0,
                 places: list[tuple[str, float, float]] | None = None) -> Path:
    """Write query images + ``queries.csv`` (file, lat, lon ground truth) of ``places`` (default:
    every shipped image); returns the CSV."""
    from vlm_vpr_ros.files.csvio import write_csv_atomic
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv

    qdir = out_dir / "queries"
    qdir.mkdir(parents=True, exist_ok=True)
    rows = []
    if places is None:
        places = read_coords_csv(DEMO_DATA / "coords.csv")
    for i, (f, lat, lon) in enumerate(places):
        rng = np.random.default_rng([seed, i])
        q = make_query(load_image(DEMO_DATA / "images" / f), rng)
        cv2.imwrite(str(qdir / f), cv2.cvtColor(q, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, 85])
        rows.append({"file": f, "lat": lat, "lon": lon})
    csv_path = out_dir / "queries.csv"
    write_csv_atomic(csv_path, ["file", "lat", "lon"], rows)
    return csv_path


def run_step(ref_map, runs: dict[str, Run], files: list[str], qdesc: np.ndarray,
             queries_csv: Path, out: Path, verifier=None, qlocal: list | None = None
             ) -> tuple[dict, dict]:
    """Localize the described queries once per run (``name -> Run``); verified runs use
    ``verifier`` (on ``ref_map``) with the queries' local features ``qlocal``. Writes
    ``out/results_<i>.csv``; returns (summaries, per-run errors/coverage/fixes); a verified
    run's summary carries its ``fixes`` (None for the others)."""
    from vlm_vpr_ros.evaluation.results_csv import evaluate_results_csv
    from vlm_vpr_ros.files.csvio import write_csv_atomic
    from vlm_vpr_ros.localization.batch import RESULT_FIELDS
    from vlm_vpr_ros.localization.localizer import Localizer
    from vlm_vpr_ros.localization.query_descriptors import localize_descriptors
    from vlm_vpr_ros.priors import create_prior_provider
    from vlm_vpr_ros.priors.simple import read_prior_csv

    priors_csv = DEMO_DATA / "priors_osv5m_baseline.csv"
    summaries, extras = {}, {}
    for i, (name, run) in enumerate(runs.items()):
        res = out / f"results_{i}.csv"
        if run.config is None:
            pri = read_prior_csv(priors_csv)
            write_csv_atomic(res, ["file", "lat", "lon"],
                             [{"file": f, "lat": pri[f][0], "lon": pri[f][1]} for f in files])
        else:
            provider = (create_prior_provider("recorded", {"path": str(priors_csv)})
                        if run.prior else create_prior_provider("none"))
            try:
                rows = list(localize_descriptors(
                    Localizer(ref_map, run.config), provider, files, qdesc,
                    verifier=verifier if run.verify else None, policy=run.status,
                    local=qlocal if run.verify else None))
            finally:
                provider.close()
            write_csv_atomic(res, RESULT_FIELDS, rows)
        summary, extras[name] = evaluate_results_csv(res, queries_csv, THRESHOLDS)
        summaries[name] = {**summary, "fixes": extras[name]["fixes"] if run.verify else None}
        extras[name]["results_csv"] = str(res)
    return summaries, extras


def calibration_note(verifier) -> str:
    """One line on what p_correct can reach on the verifier's map."""
    n = len(verifier.model.null_scores)
    if not n:
        return "      p_correct: this map is not calibrated, so no answer is a fix"
    return (f"      p_correct: calibrated by {verifier.calibration_source} on this map's "
            f"references ({n} wrong answers),\n      so it is at most 1 - 1/{n + 1} = "
            f"{1.0 - 1.0 / (n + 1):.3f}")


def lookalike_note(table: dict) -> str:
    """What the look-alike table shows, from its numbers."""
    acc = {k: table[k]["accuracy"]["0.025km"] for k in (VPR, FUSED)}
    fx, ft = table[FUSED]["fixes"], table[TRUSTED]["fixes"]
    prec = "-" if ft["precision25_pct"] is None else f"{ft['precision25_pct']:.0f} %"
    return (f"      at 25 m the prior turns {acc[FUSED] - acc[VPR]:+.1f} points of wrong "
            f"look-alikes into right answers;\n      fixes by default: {fx['n']}. A place and "
            "its look-alike give about the same inliers, so only\n      the prior tells them "
            "apart, and an answer that rests on the prior is no fix unless\n      "
            f"trust_prior_for_fix is set (last row: {ft['n']} fixes, {prec} of them within "
            "25 m: as right as the prior)")


def run_demo(out: str | Path, with_bag: bool = True, places: int | None = None) -> int:
    """The demo (module docstring) into ``out``; ``places``: only the first so many shipped
    images (a small case for tests and ``scripts/check_cpu_paths.py``: no figures; the
    tables' titles still name the whole set)."""
    from vlm_vpr_ros.evaluation.lookalike import build_lookalike_map, twin_ties, write_refs
    from vlm_vpr_ros.evaluation.metrics import format_cells, format_table
    from vlm_vpr_ros.files.atomic import atomic_save_npy
    from vlm_vpr_ros.files.csvio import read_file_column, write_csv_atomic
    from vlm_vpr_ros.localization.localizer import LocalizerConfig
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.localization.verification.stage import Verifier
    from vlm_vpr_ros.mapping.build_images import build_map
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv

    out = Path(out)
    t0, cpu0 = time.monotonic(), time.process_time()
    n_steps = 5 if with_bag else 4
    rows = read_coords_csv(DEMO_DATA / "coords.csv")
    coords_csv = DEMO_DATA / "coords.csv"
    if places is not None:
        rows = rows[:places]
        coords_csv = out / "coords.csv"
        out.mkdir(parents=True, exist_ok=True)
        write_csv_atomic(coords_csv, ["file", "lat", "lon"],
                         [{"file": f, "lat": la, "lon": lo} for f, la, lo in rows])
    n = len(rows)
    print(f"[1/{n_steps}] building the demo map from {DEMO_DATA / 'images'} ({n} images, "
          "country submaps) ...", flush=True)
    map_dir = out / "map"
    with progress_lines(f"[1/{n_steps}] building the demo map"):
        build_map(DEMO_DATA / "images", coords_csv, map_dir, partition="country",
                  overwrite=True, progress=sys.stdout.isatty())
    print(f"[2/{n_steps}] writing {n} query images (new crops, light, blur, noise, JPEG) and "
          "describing them ...", flush=True)
    with progress_lines(f"[2/{n_steps}] queries"):
        queries = make_queries(out, places=rows)
        files = read_file_column(queries)
        pipe = LocalizationPipeline.open(map_dir)
        described = [pipe.describe_query(load_image(out / "queries" / f)) for f in files]
    qdesc = np.stack([q.desc for q in described])
    qlocal = [q.local for q in described]  # the same SIFT pass, for verification
    atomic_save_npy(out / "queries_descriptors.npy", qdesc)  # rows of queries.csv
    paper = LocalizerConfig(fusion="paper")
    print(f"[3/{n_steps}] localizing the queries on the demo map ...", flush=True)
    runs = {VPR: Run(paper, prior=False), PRIOR: Run(None),
            PAPER: Run(paper), FUSED: Run(LocalizerConfig(fusion="posterior"), verify=True)}
    (out / "results").mkdir(parents=True, exist_ok=True)
    tables, extras = {}, {}
    with progress_lines(f"[3/{n_steps}] localizing"):
        tables["map"], extras["map"] = run_step(pipe.map, runs, files, qdesc, queries,
                                                out / "results", pipe.verifier, qlocal)
    print("\n" + format_table(tables["map"], title=TITLES["map"]), flush=True)
    print(FIX_MEANING + "\n" + calibration_note(pipe.verifier) + "\n", flush=True)
    print(f"[4/{n_steps}] the look-alike step: 2 mild copies of every shipped image, each at its "
          f"place and at a look-alike place 5000 km away ({4 * n} references) ...", flush=True)
    look = out / "lookalike"
    with progress_lines(f"[4/{n_steps}] the look-alike step"):
        refs = write_refs(DEMO_DATA / "images", rows, look)
        look_map = build_lookalike_map(pipe, refs, look / "refs", look / "map")
        (look / "results").mkdir(parents=True, exist_ok=True)
        look_verifier = Verifier(look_map)
        tables["lookalike"], extras["lookalike"] = run_step(
            look_map, {VPR: Run(paper, prior=False), PRIOR: Run(None), PAPER: Run(paper),
                       FUSED: Run(LocalizerConfig(), verify=True),
                       TRUSTED: Run(LocalizerConfig(), verify=True,
                                    status=StatusPolicy(trust_prior_for_fix=True))},
            files, qdesc, queries, look / "results", look_verifier, qlocal)
    tied, answered = twin_ties(look_map, qdesc)
    print(f"      VPR cannot tell a place from its look-alike (the same image): for {tied} of "
          f"{answered} queries\n      the best match's twin is at the bit-identical distance; "
          "the search breaks the tie by map order\n      (submap, then row)", flush=True)
    if tied != answered:
        log.warning("look-alike step: %d of %d queries without an exact twin tie; the VPR-only "
                    "row may differ between machines", answered - tied, answered)
    print("\n" + format_table(tables["lookalike"], title=TITLES["lookalike"]))
    print(lookalike_note(tables["lookalike"]) + "\n" + calibration_note(look_verifier) + "\n",
          flush=True)
    figures = _figures(out, files, extras["lookalike"]) if places is None else {}
    if with_bag:
        with progress_lines(f"[{n_steps}/{n_steps}] the demo bag"):
            tables["bag"], bag_outputs = _bag_demo(out, map_dir, queries, n_steps)
        figures.update(bag_outputs)
    head, body = fixes_table(tables)
    print("\n" + format_cells(head, body, TITLES["fixes"]) + "\n")
    integ = _integrity(out, queries, extras, with_bag)
    _write_json(out, tables, extras, figures, time.monotonic() - t0, integ)
    print(f"done in {time.monotonic() - t0:.0f} s wall, {time.process_time() - cpu0:.0f} s CPU; "
          f"tables in {out / 'demo.json'}, outputs in {out}/", flush=True)
    return 0


def fixes_table(tables: dict) -> tuple[list[str], list[list[str]]]:
    """The verified rows of every step, with their accuracy at 25 m and their fix columns (the
    cells of :func:`~vlm_vpr_ros.evaluation.metrics.table_cells`)."""
    from vlm_vpr_ros.evaluation.metrics import table_cells

    rows = {f"{label}: {name}": s for step, label in FIX_STEPS
            for name, s in tables.get(step, {}).items() if s.get("fixes") is not None}
    head, body = table_cells(rows)
    keep = [head.index(c) for c in FIX_TABLE_COLUMNS]
    return [head[i] for i in keep], [[r[i] for i in keep] for r in body]


def _figures(out: Path, files: list[str], extras: dict) -> dict:
    from vlm_vpr_ros.evaluation.lookalike import contact_sheet
    from vlm_vpr_ros.evaluation.plots import plot_error_cdf

    errs = {name: e["errors_km"] for name, e in extras.items()}
    cdf = plot_error_cdf(out / "lookalike" / "error_cdf.png", errs, thresholds_km=THRESHOLDS,
                         title=f"Look-alike step: error CDF ({len(files)} queries)")
    sheet = contact_sheet(out, files, extras[VPR], extras[FUSED], extras[PRIOR],
                          out / "lookalike" / "contact_sheet.png")
    print(f"      error CDF: {cdf}\n      contact sheet: {sheet}\n", flush=True)
    return {"lookalike_error_cdf_png": str(cdf), "lookalike_contact_sheet_png": str(sheet)}


def _bag_demo(out: Path, map_dir: Path, queries: Path, n_steps: int) -> tuple[dict, dict]:
    from vlm_vpr_ros.bags.bag_demo import run_bag_demo
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


def _integrity(out: Path, queries: Path, extras: dict, with_bag: bool) -> dict:
    """The integrity table (docs/evaluation.md "Integrity") of the verified runs, printed."""
    from vlm_vpr_ros.evaluation.integrity_tables import demo_integrity
    from vlm_vpr_ros.evaluation.metrics import format_cells

    runs = {f"{label}: {name}": e["results_csv"] for step, label in FIX_STEPS
            for name, e in extras[step].items() if name in (FUSED, TRUSTED)}
    if with_bag:
        runs["bag: " + FUSED] = out / "bag_demo" / "evaluation" / "frames.csv"
    integ = demo_integrity(out / "integrity", queries, runs)
    print(format_cells(integ["table"]["columns"], integ["table"]["rows"],
                       integ["table"]["title"]) + "\n", flush=True)
    return integ


def _write_json(out: Path, tables: dict, extras: dict, figures: dict, elapsed: float,
                integrity: dict | None = None) -> None:
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
    head, body = fixes_table(tables)
    doc["tables"]["fixes"] = {"columns": head, "rows": body}  # no title: short README
    if integrity is not None:  # docs table "demo integrity.table"; figure: stanford_png
        doc["integrity"] = integrity
        doc["figures"]["stanford_png"] = integrity["outputs"].get("stanford_png")
    atomic_write_json(out / "demo.json", doc)
