"""The demo's look-alike step: a map where every place has a look-alike far away.

Built from the shipped images, and said so in the demo's output: for each of the 71 places,
two independent mild copies of its one image (an 85-95 % crop resized back, a small brightness
and contrast change, JPEG), the second :data:`SECOND_PHOTO_M` north of the first (two photos
of a mapped route). Each copy is in the map twice: at the place, and at a look-alike place
:data:`LOOKALIKE_KM` away in a random, seeded direction — the same image, so the same global
descriptor and local features, bit for bit (described once, the twin's row is a copy). VPR
therefore cannot tell a place from its look-alike: the two are at exactly the same descriptor
distance from any query, on every machine, and the search breaks such a tie by a stated rule,
the map's order (submap, then row; :mod:`vlm_vpr_ros.maps.search`), so "VPR only" is right
exactly where the place's submap comes before its look-alike's (country submaps: the country
codes' alphabetical order) — about half the places, and the same half on every machine. A prior
that is closer to the true place than to the look-alike tells them apart. This is the situation
the method is for (similar streets, buildings and chains in many cities), shrunk to a
284-reference map.

Why exact twins: with four independent copies the choice between a place and its look-alike
rested on distance differences of the order of the descriptor's floating-point differences
between CPUs (SIMD paths of OpenCV, FAISS and OpenBLAS), and the demo's table changed from one
machine to another. :func:`twin_ties` checks the tie on the built map.

The references are written as images with a coordinates CSV (``refs/``, ``refs.csv``), described
with the demo map's fitted descriptor and assembled into a map folder with its fusion
calibration, exactly as ``build-map`` finishes a map.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.geodesy import EARTH_RADIUS_KM, destination

log = logging.getLogger(__name__)

#: distance between a place and its look-alike (km)
LOOKALIKE_KM = 5000.0
#: the second photo of a place (and of its look-alike) lies this far north of the first (m)
SECOND_PHOTO_M = 10.0
#: sub-folders of ``refs/``: two photos at the place, two at the look-alike place
COPIES = (("place", 0), ("place", 1), ("lookalike", 0), ("lookalike", 1))
#: leave-one-out queries of the look-alike map's p_correct calibration (build-map takes up to
#: 400; 100 keep the demo short and give ~70 wrong answers, enough for p_correct >= 0.95)
LOO_QUERIES = 100


@dataclass(frozen=True)
class LookalikeRef:
    id: str  # path under refs/, e.g. "place1/123.jpg"
    source: str  # the shipped image it is a copy of
    lat: float
    lon: float
    lookalike: bool  # True: at the look-alike place, not where the photo was taken

    @property
    def image(self) -> str:
        """The reference whose image (and descriptor) this one has: a look-alike has its
        place's copy, byte for byte."""
        return self.id.replace("lookalike", "place", 1) if self.lookalike else self.id


def twin_id(ref_id: str) -> str:
    """The other reference with the same image: place<k>/f <-> lookalike<k>/f."""
    if ref_id.startswith("lookalike"):
        return ref_id.replace("lookalike", "place", 1)
    return ref_id.replace("place", "lookalike", 1)


def mild_copy(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Another photo of the same view: 85-95 % crop resized to 640x480, brightness and
    contrast within a few percent."""
    h, w = image.shape[:2]
    s = rng.uniform(0.85, 0.95)
    ch, cw = int(h * s), int(w * s)
    y0, x0 = rng.integers(0, h - ch + 1), rng.integers(0, w - cw + 1)
    crop = cv2.resize(image[y0:y0 + ch, x0:x0 + cw], (640, 480), interpolation=cv2.INTER_AREA)
    x = crop.astype(np.float32) / 255.0
    x = np.clip(x * rng.uniform(0.85, 1.1) + rng.uniform(-0.04, 0.04), 0, 1)
    return (x * 255).round().astype(np.uint8)


def lookalike_refs(places: list[tuple[str, float, float]], seed: int = 0) -> list[LookalikeRef]:
    """The 4 references of every place (ids, coordinates), in a fixed order."""
    rng = np.random.default_rng([seed, 1])
    out = []
    north_deg = SECOND_PHOTO_M / 1000.0 / EARTH_RADIUS_KM * 180.0 / np.pi
    for f, lat, lon in places:
        twin = destination(lat, lon, LOOKALIKE_KM, float(rng.uniform(0.0, 360.0)))
        for where, k in COPIES:
            la, lo = twin if where == "lookalike" else (lat, lon)
            out.append(LookalikeRef(f"{where}{k + 1}/{f}", f, la + k * north_deg, lo,
                                    where == "lookalike"))
    return out


def write_refs(images_dir: Path, places: list[tuple[str, float, float]], out: Path,
               seed: int = 0) -> list[LookalikeRef]:
    """Write ``out/refs/<copy>/<file>`` (JPEG; a look-alike's file is its place's copy, the
    same bytes) and ``out/refs.csv`` (file, lat, lon)."""
    from vlm_vpr_ros.files.atomic import atomic_write_bytes
    from vlm_vpr_ros.files.csvio import write_csv_atomic

    refs = lookalike_refs(places, seed)
    written: dict[str, bytes] = {}
    for i, ref in enumerate(refs):
        if i % len(COPIES) == 0:
            image = load_image(images_dir / ref.source)
        if ref.image not in written:
            copy = mild_copy(image, np.random.default_rng([seed, 2, i]))
            ok, data = cv2.imencode(".jpg", cv2.cvtColor(copy, cv2.COLOR_RGB2BGR),
                                    [cv2.IMWRITE_JPEG_QUALITY, 90])
            written[ref.image] = data.tobytes()
        (out / "refs" / ref.id).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(out / "refs" / ref.id, written[ref.image])
    write_csv_atomic(out / "refs.csv", ["file", "lat", "lon"],
                     [{"file": r.id, "lat": r.lat, "lon": r.lon} for r in refs])
    return refs


def build_lookalike_map(pipe, refs: list[LookalikeRef], refs_dir: Path, map_dir: Path):
    """Describe the references with ``pipe``'s descriptor and write the map (country submaps,
    fusion calibration, local features from the same SIFT pass and the leave-one-out
    calibration of ``p_correct`` on :data:`LOO_QUERIES` references, as ``build-map`` does) to
    ``map_dir``; returns the opened :class:`ReferenceMap`."""
    from vlm_vpr_ros.files.outputs import StagedOutput
    from vlm_vpr_ros.mapping.local_features import ReferenceExtractor
    from vlm_vpr_ros.mapping.assemble import assemble_map
    from vlm_vpr_ros.mapping.build_images import write_local_features, write_map_calibration
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    refx = ReferenceExtractor(pipe.descriptor, "sift")
    described, local = {}, {}
    for r in refs:  # each image once: a look-alike gets its place's very arrays
        if r.image not in described:
            d, f = refx.describe([load_image(refs_dir / r.image)])
            described[r.image], local[r.image] = d[0], f[0]
        local[r.id] = local[r.image]
    desc = np.stack([described[r.image] for r in refs])
    coords = np.array([(r.lat, r.lon) for r in refs], dtype=np.float64)
    ref_map = assemble_map(desc, coords, [r.id for r in refs], pipe.map.descriptor_identity,
                           pipe.map.descriptor_state, "country",
                           extra={"demo": f"look-alike map: {len(refs)} copies of the shipped "
                                          f"images, look-alikes {LOOKALIKE_KM:g} km away"})
    with StagedOutput(map_dir, "map", overwrite=True) as stage:
        ref_map.save(stage.path)
        write_map_calibration(ref_map, desc, coords)
        write_local_features(ref_map, refx, local.__getitem__, loo_queries=LOO_QUERIES,
                             images_dir=refs_dir)
        stage.commit(validate=ReferenceMap.load)
    return ReferenceMap.load(map_dir)


def twin_ties(ref_map, qdesc: np.ndarray, k: int = 8) -> tuple[int, int]:
    """(queries whose best match's twin is at the bit-identical squared distance, queries
    with a best match): the tie :func:`build_lookalike_map` builds, as the map's search sees
    it (no prior, all submaps)."""
    everything = list(range(len(ref_map.submaps)))
    tied = answered = 0
    for q in np.asarray(qdesc, np.float32):
        found = ref_map.search_submaps(everything, q.reshape(1, -1), k)
        if not found:
            continue
        answered += 1
        ids = [(ref_map.submaps[si].ids[j], d) for d, si, j in found]
        best, dist = ids[0]
        tied += any(i == twin_id(best) and d == dist for i, d in ids[1:])
    return tied, answered


def _caption(ref_id: str, err_km: float | None) -> tuple[str, bool]:
    if not ref_id or err_km is None:
        return "no answer", False
    where = "look-alike" if ref_id.startswith("lookalike") else "true place"
    ok = err_km <= 0.025
    return (f"{where}: {err_km * 1000:.0f} m off" if ok else
            f"{where}: {err_km:,.0f} km off"), ok


def pick_rows(vpr_errs: list, fused_errs: list, n: int = 6) -> list[int]:
    """Queries for the contact sheet, in file order: VPR wrong and fused right first, then one
    both got right, then fused wrong (if any), so the sheet shows the failures too."""
    def ok(e):
        return e is not None and e <= 0.025

    idx = range(len(vpr_errs))
    fixed = [i for i in idx if not ok(vpr_errs[i]) and ok(fused_errs[i])]
    both = [i for i in idx if ok(vpr_errs[i]) and ok(fused_errs[i])]
    missed = [i for i in idx if not ok(fused_errs[i])]
    pick = fixed[:n - 3] + both[:1] + missed[:2]
    rest = [i for i in fixed + both if i not in pick]
    return sorted(pick + rest[:n - len(pick)])


def contact_sheet(out: Path, files: list[str], vpr: dict, fused: dict, prior: dict,
                  path: Path) -> Path:
    """Queries of the look-alike step beside the reference VPR alone matched and the one the
    fused answer chose (``vpr``/``fused``/``prior``: the demo's per-run extras)."""
    from vlm_vpr_ros.evaluation.plots import SheetCell, plot_contact_sheet
    from vlm_vpr_ros.files.csvio import read_table

    ref_ids = {name: [r.get("ref_id", "") for r in read_table(e["results_csv"], ("file",),
                                                               "results CSV")]
               for name, e in (("vpr", vpr), ("fused", fused))}
    blank = np.full((480, 640, 3), 235, np.uint8)
    rows = []
    for i in pick_rows(vpr["errors_km"], fused["errors_km"]):
        pe = prior["errors_km"][i]
        cells = [SheetCell(load_image(out / "queries" / files[i]),
                           f"query {i + 1}; prior {pe:,.0f} km off" if pe is not None
                           else f"query {i + 1}; no prior")]
        for name, extra in (("vpr", vpr), ("fused", fused)):
            rid = ref_ids[name][i]
            text, ok = _caption(rid, extra["errors_km"][i])
            cells.append(SheetCell(load_image(out / "lookalike" / "refs" / rid) if rid
                                   else blank, text, ok))
        rows.append(cells)
    return plot_contact_sheet(path, rows, ["query", "VPR only: best match",
                                           "prior+VPR (default): answer"],
                              title="Look-alike step: the match each method chose (green: "
                                    "within 25 m, red: wrong)")
