"""``p_correct``: the probability that a verified answer is right (within the place radius),
calibrated on the map's own references and refined on a user's labelled queries.

Build time (:func:`loo_calibration`): up to ``max_queries`` references (half of them among
those with another reference within the place radius, when there are any) are used as queries
against the rest of the map — retrieval with the map's own index, the copy of the image and
exact duplicates left out, verification of the top K with the stored features — and the
evidence score (:mod:`.evidence`) of each answer is kept with whether it was right.

Many maps have no two references of one place (the 71-image demo map: none within 25 m), so
leave-one-out mostly yields *wrong* answers. The calibration therefore rests on them only:
``p_correct(s) = 1 - (1 + #{wrong scores >= s}) / (1 + #wrong)``, the conformal p-value of the
score under "this answer is wrong". For a wrong answer exchangeable with the leave-one-out
ones, ``P(p_correct >= 0.95) <= 5 %``: the threshold bounds the false-fix rate among wrong
answers, whatever the share of right ones. It never claims what it has not seen: with fewer
than 19 wrong answers no score reaches 0.95, and an uncalibrated map gives NaN (never a fix).

Query conditions (:mod:`.conditions`): besides the stored references (``full``), degraded
copies of reference images (fitted inside 640×480 / 480×360, JPEG q40) are queries too, so that
the wrong answers cover the frames a robot sends; their scores are pooled. The default fix
threshold 0.99 needs >= 99 wrong answers; the degraded copies supply them on small maps
(docs/verification.md section 2). The document (version 2) also holds the protection level's
residual (:func:`protection_residual`); version 1 files (full size only) still load.

``vlm-vpr calibrate`` adds the wrong answers among a user's labelled queries (real queries of
the deployment: the most relevant negatives) to the set (the ``user`` section).

The radius of a verified answer: a right answer lies within the place radius of the truth,
taken as uniform over the place disc (``r_q = R sqrt(q)``). See :func:`verified_radius`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Collection, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.geodesy import EARTH_RADIUS_KM, haversine_km, latlon_to_unit
from vlm_vpr_ros.localization.verification.evidence import AMBIGUOUS_RATIO, EvidenceConfig, \
    weigh
from vlm_vpr_ros.maps.documents import load_document, save_document
from vlm_vpr_ros.types import LocalFeatures

log = logging.getLogger(__name__)

VERIFY_CAL_FILE = "verification.json"
VERIFY_CAL_FORMAT = "vlm_vpr_ros.verification_calibration"
VERIFY_CAL_VERSION = 2
#: versions that load (1: before query conditions and protection levels: full size only)
VERIFY_CAL_VERSIONS = (1, 2)
#: integrity risk the protection level is stated at (docs/verification.md section 3)
INTEGRITY_RISK = 1e-3
#: a verified candidate supports the answer (the scene is visible from there) when it holds at
#: least this share of the winner's inliers, above the noise level
SUPPORT_SHARE = 0.25
#: the matcher's noise level is measured on this many random pairs of references at least
#: NOISE_MIN_DISTANCE_M apart (unrelated views), as the NOISE_QUANTILE of their inliers: the
#: 95th percentile stays clear of the 1-2 % of pairs that are real views of one scene (a
#: landmark seen from far; the demo's look-alike map, where every scene is in the map four
#: times: 99th percentile 154 inliers, 95th 10)
NOISE_PAIRS = 300
NOISE_MIN_DISTANCE_M = 250.0
NOISE_QUANTILE = 0.95
#: the strongest wrong leave-one-out answers kept in the document (what sets the threshold; a
#: user's map with references of one view geotagged far apart shows them: `vlm-vpr calibrate`)
STRONGEST_WRONG = 10
#: the competitor floor is never below this: MAGSAC fits 8-12 "inliers" among pure noise
#: (tests/test_verification.py), the floor the SIFT calibration was built on
MIN_COMPETITOR_FLOOR = 12


@dataclass
class PCorrect:
    """The calibrated map from evidence score to ``p_correct`` (module docstring)."""

    null_scores: np.ndarray  # scores of wrong answers, sorted ascending
    place_radius_m: float = 25.0
    source: str = "none"
    #: what the protection level adds to the support spread (m; calibration_doc)
    residual_m: float = 25.0
    integrity_risk: float = INTEGRITY_RISK
    #: query conditions calibrated for (empty: a version-1 map, full size only, unrecorded)
    conditions: tuple[str, ...] = ()
    min_long_side_px: int = 0  # smallest calibrated frame's longer side (0: unknown)

    @property
    def calibrated(self) -> bool:
        return len(self.null_scores) > 0

    def p_correct(self, score: float) -> float:
        n = len(self.null_scores)
        if n == 0 or not math.isfinite(score):
            return math.nan
        above = n - int(np.searchsorted(self.null_scores, score, side="left"))
        p = 1.0 - (1.0 + above) / (1.0 + n)
        if score < AMBIGUOUS_RATIO:  # another place holds half the winner's evidence or more
            p = min(p, score / (1.0 + score))
        return p

    def place_quantile(self, q: float) -> float:
        """Radius (m) holding fraction ``q`` of right answers' errors: uniform over the place
        disc, ``R sqrt(q)`` (a right answer is anywhere within the place radius; the errors of
        right leave-one-out answers, between two references, understate a query's)."""
        return float(self.place_radius_m * math.sqrt(min(max(q, 0.0), 1.0)))

    @classmethod
    def from_doc(cls, doc: Mapping[str, Any] | None) -> "PCorrect":
        if not doc:
            return cls(np.zeros(0))
        null = list(doc.get("null_scores", [])) + list((doc.get("user") or {})
                                                        .get("null_scores", []))
        n_loo = int((doc.get("loo") or {}).get("queries", 0))
        n_user = int((doc.get("user") or {}).get("queries", 0))
        src = f"map leave-one-out ({n_loo} queries)" if n_loo else "none"
        if n_user:
            src += f" + user ({n_user} labelled queries)"
        radius = float(doc.get("place_radius_m", 25.0))
        prot = doc.get("protection") or {}
        return cls(np.sort(np.asarray(null, np.float64)), radius, src,
                   max(radius, float(prot.get("residual_m", radius))),
                   float(prot.get("integrity_risk", INTEGRITY_RISK)),
                   tuple(doc.get("conditions") or ()), int(doc.get("min_long_side_px") or 0))


def verified_radius(model: PCorrect, p: float, q: float, fallback_m: float,
                    level: float) -> float:
    """Radius (m) holding the truth with probability ``q``. An answer verified at ``p_correct
    >= level`` (the fix threshold: there the bound on wrong answers holds) is right with
    probability ``p``: the place's error quantile ``q / p`` when ``p >= q``. Anything else keeps
    the (posterior's) ``fallback_m``: ``p_correct`` below the threshold is no probability to
    narrow a radius with."""
    if not (math.isfinite(p) and p >= max(q, level)):
        return fallback_m
    return min(model.place_quantile(q / p), fallback_m)


def sample_queries(coords: np.ndarray, max_queries: int, place_radius_m: float,
                   rng: np.random.Generator) -> np.ndarray:
    """Rows used as leave-one-out queries: half among references with another within the place
    radius (so right answers can occur), the rest among all."""
    n = len(coords)
    xyz = latlon_to_unit(coords[:, 0], coords[:, 1])
    cos_r = math.cos(place_radius_m / 1000.0 / EARTH_RADIUS_KM)
    twin = np.zeros(n, bool)
    for chunk in np.array_split(np.arange(n), max(1, n // 2048)):
        near = (xyz[chunk] @ xyz.T) >= cos_r
        near[np.arange(len(chunk)), chunk] = False
        twin[chunk] = near.any(1)
    k = min(n, max_queries)
    pool = np.flatnonzero(twin)
    first = rng.choice(pool, size=min(len(pool), k // 2), replace=False)
    rest = np.setdiff1d(np.arange(n), first)
    second = rng.choice(rest, size=min(len(rest), k - len(first)), replace=False)
    return np.sort(np.concatenate([first, second]).astype(np.int64))


#: (query condition, query row, candidate rows, their inlier counts) of one leave-one-out query
LooRecord = tuple[str, int, list[int], np.ndarray]
#: (search result [(squared distance, row)], local features) of a degraded query, per condition
Degraded = Callable[[int], Mapping[str, tuple[list[tuple[float, int]], LocalFeatures]]]


def noise_pairs(coords: np.ndarray, n: int, min_distance_m: float,
                rng: np.random.Generator,
                copies_of: Callable[[int], Collection[int]] | None = None
                ) -> list[tuple[int, int]]:
    """Up to ``n`` distinct random pairs of rows at least ``min_distance_m`` apart (unrelated
    views: their inliers are the matcher's noise); fewer on a map without such pairs.
    ``copies_of(row)``: rows holding the same photograph (a look-alike copy far away is no
    unrelated view: it matches with every keypoint), never paired."""
    m = len(coords)
    if m < 2:
        return []
    seen: set[tuple[int, int]] = set()
    out: list[tuple[int, int]] = []
    for _ in range(20 * n):
        i, j = (int(v) for v in rng.choice(m, size=2, replace=False))
        key = (min(i, j), max(i, j))
        if key in seen or (copies_of is not None and j in copies_of(i)):
            continue
        seen.add(key)
        d = float(haversine_km(coords[i, 0], coords[i, 1], coords[j, 0], coords[j, 1])) * 1e3
        if d >= min_distance_m:
            out.append((i, j))
            if len(out) == n:
                break
    return out


def noise_level(counts: Sequence[int], minimum: int = MIN_COMPETITOR_FLOOR) -> dict[str, Any]:
    """The matcher's noise level from the inliers of unrelated pairs: the competitor floor is
    their NOISE_QUANTILE (at least ``minimum``; ``minimum`` alone without pairs)."""
    c = np.asarray(counts, np.int64)
    if not len(c):
        return {"pairs": 0, "median": None, "p95": None, "max": None, "floor": int(minimum)}
    q = int(np.quantile(c, NOISE_QUANTILE, method="higher"))
    return {"pairs": int(len(c)), "median": float(np.median(c)), "p95": q, "max": int(c.max()),
            "floor": max(int(minimum), q)}


def loo_records(coords: np.ndarray, search: Callable[[int, int], list[tuple[float, int]]],
                features_of: Callable[[int], LocalFeatures],
                inliers_of: Callable[[LocalFeatures, Sequence[LocalFeatures]], np.ndarray],
                top_k: int, cfg: EvidenceConfig = EvidenceConfig(), max_queries: int = 150,
                seed: int = 0, progress: Callable[[int, int], None] | None = None,
                conditions: Sequence[str] = ("full",), degraded: Degraded | None = None,
                degraded_queries: int | None = None,
                copies_of: Callable[[int], Collection[int]] | None = None) -> list[LooRecord]:
    """The leave-one-out queries (:func:`loo_calibration`): ``full`` queries with the stored
    features of up to ``max_queries`` references; the other ``conditions`` through
    ``degraded(row)`` (the degraded copies of that reference's image, described and searched)
    on ``degraded_queries`` of the same references (default: all of them).

    ``copies_of(row)``: the other rows that hold the *same photograph* (bit-identical global
    descriptors), left out with the query. A held-out photo still in the map under another
    position is no independent view of anything: it would match itself, a thing no real
    query does, and make a copy at a look-alike place 5,000 km away look like a confident
    wrong answer. The ambiguity such copies carry is still calibrated: the *other* photos of
    the place meet both copies, with equal inliers (``search`` and ``degraded`` must return
    ``top_k`` + 1 + the largest number of copies rows)."""
    coords = np.asarray(coords, np.float64)
    rng = np.random.default_rng(seed)
    rows = sample_queries(coords, max_queries, cfg.place_radius_m, rng) if len(coords) > 2 \
        else np.zeros(0, np.int64)
    others = [c for c in conditions if c != "full"] if degraded is not None else []
    n_deg = len(rows) if degraded_queries is None else min(len(rows), int(degraded_queries))
    deg_rows = np.sort(rng.choice(rows, size=n_deg, replace=False)) if others and n_deg \
        else np.zeros(0, np.int64)
    jobs = ([("full", r) for r in rows.tolist()] if "full" in conditions else []) + \
        [("*", r) for r in deg_rows.tolist()]
    out: list[LooRecord] = []

    def one(cond: str, qi: int, found: list[tuple[float, int]], feat: LocalFeatures) -> None:
        left_out = {qi, *(copies_of(qi) if copies_of is not None else ())}
        cand = [j for _, j in found if j not in left_out][:top_k]
        if cand:
            out.append((cond, qi, cand, np.asarray(
                inliers_of(feat, [features_of(j) for j in cand]), np.int64)))

    for done, (cond, qi) in enumerate(jobs):
        if cond == "full":
            extra = len(copies_of(qi)) if copies_of is not None else 0
            one(cond, qi, search(qi, top_k + 1 + extra), features_of(qi))
        else:
            for name, (found, feat) in degraded(qi).items():
                if name in others:
                    one(name, qi, found, feat)
        if progress is not None:
            progress(done + 1, len(jobs))
    return out


def support_spread_m(lat: np.ndarray, lon: np.ndarray, inliers: np.ndarray, winner: int,
                     floor: int, share: float = SUPPORT_SHARE) -> float:
    """Distance (m) from the winner to the farthest candidate that verifies with substantial
    inliers (above the noise level ``floor`` and at least ``share`` of the winner's): the
    region where the query's scene is visible from (0 when only the winner verifies)."""
    inl = np.asarray(inliers, np.int64)
    need = max(floor + 1, math.ceil(share * max(int(inl[winner]), 0)))
    sup = np.flatnonzero(inl >= need)
    if not len(sup) or inl[winner] < need:
        return 0.0
    d = haversine_km(lat[winner], lon[winner], np.asarray(lat)[sup], np.asarray(lon)[sup])
    return float(np.max(np.atleast_1d(d))) * 1000.0


def loo_calibration(coords: np.ndarray, search: Callable[[int, int], list[tuple[float, int]]],
                    features_of: Callable[[int], LocalFeatures],
                    inliers_of: Callable[[LocalFeatures, Sequence[LocalFeatures]], np.ndarray],
                    top_k: int, cfg: EvidenceConfig = EvidenceConfig(),
                    max_queries: int = 150, seed: int = 0,
                    progress: Callable[[int, int], None] | None = None,
                    conditions: Sequence[str] = ("full",), degraded: Degraded | None = None,
                    degraded_queries: int | None = None,
                    min_long_side_px: int = 0,
                    copies_of: Callable[[int], Collection[int]] | None = None
                    ) -> dict[str, Any]:
    """The build-time calibration (module docstring) as a JSON-ready dict.

    ``coords``: (n, 2) positions of the references (global row order); ``search(row, k)``: the
    k nearest references of ``row`` by descriptor as (squared distance, row), itself included;
    ``features_of(row)``; ``inliers_of(query, refs)``: verified inlier counts; ``conditions``,
    ``degraded``, ``degraded_queries``: the query conditions (:func:`loo_records`);
    ``min_long_side_px``: the smallest degraded frame's longer side (0: full size only);
    ``copies_of``: other rows of the same photograph, left out with it (:func:`loo_records`)."""
    t0 = time.monotonic()
    recs = loo_records(coords, search, features_of, inliers_of, top_k, cfg, max_queries, seed,
                       progress, conditions, degraded, degraded_queries, copies_of)
    done = sorted({r[0] for r in recs} | ({"full"} if "full" in conditions else set()),
                  key=list(conditions).index)
    return calibration_doc(recs, coords, top_k, cfg, done, min_long_side_px,
                           time.monotonic() - t0)


def calibration_doc(records: Sequence[LooRecord], coords: np.ndarray, top_k: int,
                    cfg: EvidenceConfig, conditions: Sequence[str], min_long_side_px: int = 0,
                    seconds: float = 0.0) -> dict[str, Any]:
    """The ``verification.json`` document of leave-one-out ``records``: the wrong answers'
    scores (pooled over the conditions), the right answers' errors, per-condition counts and
    the protection level's residual (:func:`protection_residual`)."""
    coords = np.asarray(coords, np.float64)
    right_err, per = [], {c: {"queries": 0, "wrong": 0, "right": 0} for c in conditions}
    #: the wrong answers (score, condition, query row, answer row, error m, inliers): their
    #: scores are the null set, the strongest STRONGEST_WRONG are kept (what sets the threshold)
    wrong: list[tuple[float, str, int, int, float, int]] = []
    graded = []  # (score, error m, support spread m, place in the map) above the noise level
    xyz = latlon_to_unit(coords[:, 0], coords[:, 1]) if len(coords) else np.zeros((0, 3))
    cos_r = math.cos(cfg.place_radius_m / 1000.0 / EARTH_RADIUS_KM)
    in_map: dict[int, bool] = {}

    def mapped(qi: int) -> bool:
        """Whether another reference lies within the place radius of reference ``qi``."""
        if qi not in in_map:
            near = (xyz @ xyz[qi]) >= cos_r
            in_map[qi] = int(near.sum()) > 1
        return in_map[qi]
    for cond, qi, cand, inl in records:
        lat, lon = coords[cand, 0], coords[cand, 1]
        ev = weigh(lat, lon, inl, None, cfg)
        w = cand[ev.winner]
        err = float(haversine_km(coords[qi, 0], coords[qi, 1],
                                 coords[w, 0], coords[w, 1])) * 1000.0
        pc = per.setdefault(cond, {"queries": 0, "wrong": 0, "right": 0})
        pc["queries"] += 1
        if err <= cfg.place_radius_m:
            right_err.append(round(err, 2))
            pc["right"] += 1
        else:
            wrong.append((round(float(ev.score), 4), cond, int(qi), int(w), round(err, 1),
                          int(ev.winner_inliers)))
            pc["wrong"] += 1
        if ev.winner_inliers > cfg.competitor_floor:
            graded.append((float(ev.score), err, support_spread_m(
                lat, lon, inl, ev.winner, cfg.competitor_floor), mapped(qi)))
    null = sorted(r[0] for r in wrong)
    model = PCorrect(np.asarray(null, np.float64), cfg.place_radius_m)
    residual, n_fix = protection_residual(model, graded, cfg.place_radius_m)
    return {"format": VERIFY_CAL_FORMAT, "version": VERIFY_CAL_VERSION,
            "place_radius_m": cfg.place_radius_m, "competitor_floor": cfg.competitor_floor,
            "top_k": int(top_k), "null_scores": null,
            "place_errors_m": sorted(right_err),
            "conditions": list(conditions), "min_long_side_px": int(min_long_side_px),
            "per_condition": per,
            "protection": {"integrity_risk": INTEGRITY_RISK, "support_share": SUPPORT_SHARE,
                           "residual_m": round(residual, 1), "fix_grade_answers": n_fix},
            "loo": {"queries": len(records), "wrong": len(wrong), "right": len(right_err),
                    "seconds": round(seconds, 1)},
            "strongest_wrong": [dict(zip(("score", "condition", "query_row", "answer_row",
                                          "error_m", "inliers"), r))
                                for r in sorted(wrong, reverse=True)[:STRONGEST_WRONG]]}


def protection_residual(model: PCorrect, graded: Sequence[tuple[float, float, float, bool]],
                        place_radius_m: float, level: float = 0.95) -> tuple[float, int]:
    """(residual m, answers it rests on): what the protection level adds to the support
    spread. Among the leave-one-out answers at ``p_correct >= level`` whose query place is in
    the map (another reference within the place radius of it), the largest ``error - spread``,
    at least the place radius (a right answer is anywhere within it of the truth). Answers at
    places the map does not cover (a landmark seen from a mapped place 60-500 m away) are no
    matter of the radius: the threshold bounds them (docs/verification.md section 3)."""
    res = [e - s for sc, e, s, mapped in graded if mapped and model.p_correct(sc) >= level]
    return max([place_radius_m] + res), len(res)


def with_user_negatives(doc: Mapping[str, Any] | None, scores: Sequence[float], queries: int,
                        results: str) -> dict[str, Any]:
    """``doc`` (or a new user-only calibration) with the scores of a user's wrong answers as
    its ``user`` section (``vlm-vpr calibrate``: replaces an earlier user section)."""
    new = dict(doc) if doc else {
        "format": VERIFY_CAL_FORMAT, "version": VERIFY_CAL_VERSION, "place_radius_m": 25.0,
        "competitor_floor": EvidenceConfig().competitor_floor, "top_k": 20,
        "null_scores": [], "place_errors_m": [], "loo": {"queries": 0},
        # the user's own queries are the deployment's conditions (no frame size recorded)
        "conditions": ["user"], "min_long_side_px": 0,
        "protection": {"integrity_risk": INTEGRITY_RISK, "support_share": SUPPORT_SHARE,
                       "residual_m": 25.0, "fix_grade_answers": 0}}
    new["user"] = {"null_scores": sorted(round(float(s), 4) for s in scores),
                   "queries": int(queries), "results": results}
    return validate(new, "verification calibration")


# -- persistence ------------------------------------------------------------------------------
def validate(doc: Any, where: str) -> dict[str, Any]:
    """Structure check; MapError naming the field."""
    if not isinstance(doc, dict) or doc.get("format") != VERIFY_CAL_FORMAT:
        raise MapError(f"{where}: not a {VERIFY_CAL_FORMAT} file")
    if doc.get("version") not in VERIFY_CAL_VERSIONS:
        raise MapError(f"{where}: verification calibration version {doc.get('version')!r} "
                       "unsupported")
    for key in ("null_scores", "place_errors_m"):
        vals = doc.get(key)
        if not isinstance(vals, list) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                and v >= 0 for v in vals):
            raise MapError(f"{where}: {key} must be a list of finite numbers >= 0")
    if doc["version"] >= 2:
        conds = doc.get("conditions")
        prot = doc.get("protection")
        if not isinstance(conds, list) or not conds or not all(isinstance(c, str)
                                                               for c in conds):
            raise MapError(f"{where}: conditions must be a non-empty list of names")
        if not isinstance(prot, dict) or not _positive(prot.get("residual_m")) or not (
                _positive(prot.get("integrity_risk")) and prot["integrity_risk"] < 1):
            raise MapError(f"{where}: protection must hold residual_m > 0 and an "
                           "integrity_risk in (0, 1)")
        side = doc.get("min_long_side_px")
        if not isinstance(side, int) or isinstance(side, bool) or side < 0:
            raise MapError(f"{where}: min_long_side_px must be an integer >= 0")
    sw = doc.get("strongest_wrong", [])
    if not isinstance(sw, list) or not all(isinstance(r, dict) for r in sw):
        raise MapError(f"{where}: strongest_wrong must be a list of objects")
    user = doc.get("user")
    if user is not None and (not isinstance(user, dict)
                             or not isinstance(user.get("null_scores"), list)):
        raise MapError(f"{where}: user section malformed")
    floor = doc.get("competitor_floor", 12)
    if not isinstance(floor, int) or isinstance(floor, bool) or floor < 0:
        raise MapError(f"{where}: competitor_floor must be an integer >= 0")
    for key in ("place_radius_m", "top_k"):
        v = doc.get(key)
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not v > 0:
            raise MapError(f"{where}: {key} must be a number > 0")
    return doc


def _positive(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) \
        and v > 0


def load_doc(ref_map: Any) -> dict[str, Any] | None:
    """The map's verification.json (validated, checksum-checked) or None when it has none."""
    doc = load_document(ref_map, "verification_calibration", "verification calibration")
    return None if doc is None else validate(
        doc, f"{ref_map.path}/{ref_map.manifest['verification_calibration']}")


def save_doc(ref_map: Any, doc: Mapping[str, Any]) -> Path:
    """Write ``verification.json`` into a saved map and list it in the manifest (last)."""
    validate(dict(doc), VERIFY_CAL_FILE)
    return save_document(ref_map, "verification_calibration", VERIFY_CAL_FILE, doc,
                         "verification calibration")
