"""Calibration of the fusion: visual scale, sharpness, miss probability and conformal radii.

At build time (:func:`calibrate_references`, called once at the end of ``build_map``) the map's
own references are used as leave-one-out (LOO) queries, so no extra data is needed:

* ``visual_scale``: median over (up to 2,000) references of the standard deviation of the squared
  descriptor distances to their 10 nearest other references — the spread of look-alike scores
  (exact copies of an image, squared distance <= 1e-4, are not neighbours).
* LOO queries are the references that have another reference within ``place_radius_m`` (the
  place *is* in the map, as for a robot on a mapped route). Each is searched against all other
  references (top-p).
* ``beta``: the sharpness maximizing the LOO likelihood that the posterior puts its mass on the
  same-place candidates; ``miss_prob``: the share of LOO queries with no same-place candidate in
  the top-p.
* conformal factors ``k68`` / ``k95``: the finite-sample 68 / 95 % quantiles of
  ``error / raw_radius`` over the LOO queries, once without a prior and once with a prior drawn
  from the error model around the truth. Calibrated radius = ``max(place_radius, k * raw)``.

All of it is ONE optional file in the map folder, ``calibration.json``, listed in the manifest's
``files`` (maps without it load and use defaults: per-query visual scale, beta 1, factors 1).
``vlm-vpr calibrate`` refines the factors from a user's labelled results (a ``user`` section).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.localization.fusion.error_model import ErrorModel
from vlm_vpr_ros.localization.fusion.posterior import fuse
from vlm_vpr_ros.maps.documents import load_document, save_document
from vlm_vpr_ros.geodesy import EARTH_RADIUS_KM, haversine_km, latlon_to_unit

log = logging.getLogger(__name__)

CALIBRATION_FILE = "calibration.json"
CALIBRATION_FORMAT = "vlm_vpr_ros.fusion_calibration"
CALIBRATION_VERSION = 1
REGIMES = ("no_prior", "prior")
MAX_LOO_REFERENCES = 200_000  # above this, only the visual scale is computed (from a sample)
#: squared descriptor distances at most this are copies of the same image (re-uploads,
#: duplicated look-alikes): not neighbours in the statistics, not matches of a LOO query
DUPLICATE_SQ = 1e-4


#: least conformal factor: when most leave-one-out answers are exact (several references at
#: one position, e.g. the views of one panorama), the quantile is 0; radii are floored anyway
#: (``uncertainty_floor_m``), and a factor of 0 would make the calibration file invalid
MIN_FACTOR = 1e-3


def conformal_factor(ratios: np.ndarray, q: float) -> float:
    """Finite-sample split-conformal quantile: the ceil((n+1) q)-th smallest ratio (at least
    :data:`MIN_FACTOR`)."""
    r = np.sort(np.asarray(ratios, dtype=np.float64))
    n = len(r)
    if n == 0:
        return 1.0
    k = min(n, int(math.ceil((n + 1) * q)))
    return max(float(r[k - 1]), MIN_FACTOR)


def _sample_prior(lat: float, lon: float, model: ErrorModel,
                  rng: np.random.Generator) -> tuple[float, float]:
    """A prior drawn from ``model`` around (lat, lon): distance by inverse CDF, random bearing."""
    d = float(model.sample_km(rng, 1)[0]) / EARTH_RADIUS_KM
    b = rng.uniform(0, 2 * math.pi)
    la, lo = math.radians(lat), math.radians(lon)
    la2 = math.asin(math.sin(la) * math.cos(d) + math.cos(la) * math.sin(d) * math.cos(b))
    lo2 = lo + math.atan2(math.sin(b) * math.sin(d) * math.cos(la),
                          math.cos(d) - math.sin(la) * math.sin(la2))
    return math.degrees(la2), (math.degrees(lo2) + 540.0) % 360.0 - 180.0


def _sq_dists(desc: np.ndarray, rows: np.ndarray) -> np.ndarray:
    q = desc[rows]
    nn = (desc * desc).sum(1)
    return np.maximum(nn[None, :] + (q * q).sum(1)[:, None] - 2.0 * q @ desc.T, 0.0)


def calibrate_references(desc: np.ndarray, coords: np.ndarray, model: ErrorModel,
                         top_p: int = 50, place_radius_m: float = 25.0,
                         max_queries: int = 400, seed: int = 0) -> dict[str, Any]:
    """The build-time calibration of a map (module docstring) as a JSON-ready dict."""
    desc = np.asarray(desc, dtype=np.float32)
    coords = np.asarray(coords, dtype=np.float64)
    n = len(desc)
    rng = np.random.default_rng(seed)
    out: dict[str, Any] = {"format": CALIBRATION_FORMAT, "version": CALIBRATION_VERSION,
                           "place_radius_m": place_radius_m, "top_p": top_p,
                           "n_references": n}
    # visual scale from nearest-neighbour statistics
    sample = rng.choice(n, size=min(n, 2000), replace=False) if n > 1 else np.arange(n)
    spreads = []
    for chunk in np.array_split(sample, max(1, len(sample) // 256)):
        d = _sq_dists(desc, chunk)
        d[np.arange(len(chunk)), chunk] = np.inf
        d[d <= DUPLICATE_SQ] = np.inf  # copies of the same image are not neighbours
        k = min(10, n - 1)
        if k >= 2:
            part = np.sort(np.partition(d, k - 1, axis=1)[:, :k], axis=1)
            part = part[np.all(np.isfinite(part), axis=1)]
            spreads += list(part.std(axis=1))
    scale = float(np.median(spreads)) if spreads else 0.0
    out["visual_scale"] = scale if scale > 0 and math.isfinite(scale) else None
    out["regimes"] = {}
    out["beta"], out["miss_prob"] = 1.0, 0.05
    if n > MAX_LOO_REFERENCES or n < 3 or out["visual_scale"] is None:
        out["loo"] = {"queries": 0, "why": "map too large or too small for LOO calibration"}
        return out
    xyz = latlon_to_unit(coords[:, 0], coords[:, 1])
    cos_r = math.cos(place_radius_m / 1000.0 / EARTH_RADIUS_KM)
    has_twin = np.zeros(n, bool)
    for chunk in np.array_split(np.arange(n), max(1, n // 2048)):
        near = (xyz[chunk] @ xyz.T) >= cos_r
        near[np.arange(len(chunk)), chunk] = False
        has_twin[chunk] = near.any(1)
    pool = np.flatnonzero(has_twin)
    if len(pool) < 10:
        out["loo"] = {"queries": int(len(pool)),
                      "why": f"fewer than 10 references have another within {place_radius_m} m"}
        return out
    rows = rng.choice(pool, size=min(max_queries, len(pool)), replace=False)
    p = min(top_p, n - 1)
    cands = []
    for chunk in np.array_split(rows, max(1, len(rows) // 128)):
        d = _sq_dists(desc, chunk)
        d[np.arange(len(chunk)), chunk] = np.inf
        d[d <= DUPLICATE_SQ] = np.inf  # a copy of the query image is not a LOO match
        idx = np.argpartition(d, p - 1, axis=1)[:, :p]
        for r, (qi, ii) in enumerate(zip(chunk, idx)):
            ii = ii[np.argsort(d[r, ii], kind="stable")]
            ii = ii[np.isfinite(d[r, ii])]
            if len(ii) == 0:
                continue
            pos = (xyz[ii] @ xyz[qi]) >= cos_r
            cands.append((qi, ii, d[r, ii].astype(np.float64), pos))
    hit = [c for c in cands if c[3].any()]
    miss_prob = 1.0 - len(hit) / len(cands)
    betas = np.exp(np.linspace(math.log(0.02), math.log(50.0), 61))
    ll = []
    for b in betas:
        tot = 0.0
        for _, _, d, pos in hit:
            lw = -b * (d - d[0]) / scale
            lw -= lw.max()
            tot += math.log(max(np.exp(lw[pos]).sum() / np.exp(lw).sum(), 1e-300))
        ll.append(tot)
    beta = float(betas[int(np.argmax(ll))]) if hit else 1.0
    out["beta"], out["miss_prob"] = beta, float(min(max(miss_prob, 0.01), 0.99))
    # background of the miss component: a coarse sample of the references
    bg_rows = rng.choice(n, size=min(n, 500), replace=False)
    background = (coords[bg_rows, 0], coords[bg_rows, 1], np.ones(len(bg_rows)))
    ratios: dict[str, dict[str, list[float]]] = {r: {"68": [], "95": []} for r in REGIMES}
    for qi, ii, d, _ in cands:
        truth = coords[qi]
        for regime in REGIMES:
            prior = _sample_prior(truth[0], truth[1], model, rng) if regime == "prior" else None
            post = fuse(d, coords[ii, 0], coords[ii, 1], scale, beta, prior=prior,
                        error_model=model if prior else None, miss_prob=out["miss_prob"],
                        background=background, vote_radius_m=place_radius_m)
            b = ii[post.best]
            err_m = float(haversine_km(truth[0], truth[1], coords[b, 0], coords[b, 1])) * 1e3
            for key, raw in (("68", post.r68_m), ("95", post.r95_m)):
                ratios[regime][key].append(err_m / max(raw, place_radius_m))
    for regime in REGIMES:
        out["regimes"][regime] = {
            "k68": conformal_factor(np.array(ratios[regime]["68"]), 0.68),
            "k95": conformal_factor(np.array(ratios[regime]["95"]), 0.95),
            "n": len(ratios[regime]["68"])}
    out["loo"] = {"queries": len(cands), "with_same_place_candidate": len(hit),
                  "beta_loglik": round(float(max(ll)), 4) if hit else None}
    return out


def validate_calibration(doc: Any, where: str) -> dict[str, Any]:
    """Check the structure of a calibration dict; MapError naming the field otherwise."""
    if not isinstance(doc, dict) or doc.get("format") != CALIBRATION_FORMAT:
        raise MapError(f"{where}: not a {CALIBRATION_FORMAT} file")
    if doc.get("version") != CALIBRATION_VERSION:
        raise MapError(f"{where}: calibration version {doc.get('version')!r} unsupported")

    def num(v: Any, name: str, lo: float = 0.0) -> None:
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) \
                or v <= lo:
            raise MapError(f"{where}: {name} must be a finite number > {lo}, got {v!r}")

    if doc.get("visual_scale") is not None:
        num(doc["visual_scale"], "visual_scale")
    num(doc.get("beta"), "beta")
    num(doc.get("miss_prob"), "miss_prob")
    for section in ("regimes", "user"):
        for regime, f in (doc.get(section) or {}).items():
            if regime not in REGIMES or not isinstance(f, dict):
                raise MapError(f"{where}: {section}.{regime} is not one of {REGIMES}")
            num(f.get("k68"), f"{section}.{regime}.k68")
            num(f.get("k95"), f"{section}.{regime}.k95")
    return doc


def load_calibration(ref_map: Any) -> dict[str, Any] | None:
    """The map's calibration.json (validated, checksum-checked) or None for maps without it."""
    doc = load_document(ref_map, "calibration", "radius calibration")
    return None if doc is None else validate_calibration(
        doc, f"{ref_map.path}/{ref_map.manifest['calibration']}")


def save_calibration(ref_map: Any, doc: Mapping[str, Any]) -> Path:
    """Write ``calibration.json`` into a saved map and list it in the manifest (manifest last)."""
    validate_calibration(dict(doc), CALIBRATION_FILE)
    return save_document(ref_map, "calibration", CALIBRATION_FILE, doc, "calibration")
