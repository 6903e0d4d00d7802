"""What every map builder calls to give a map its local features and its verification
calibration (images: ``build-map``; bags: ``build-map --bag``; ``map add/remove``; Ray).

* :class:`ReferenceExtractor`: the global descriptor and the local features of reference
  images, in one SIFT pass for vlad_rootsift maps with the ``sift`` preset and one XFeat pass
  for vlad_xfeat maps verified with XFeat (``xfeat_mnn``, ``xfeat_lighterglue``).
* :func:`store_features`: write a saved map's feature files (:mod:`vlm_vpr_ros.maps.features`)
  from the features of each reference id.
* :func:`calibrate_map`: the leave-one-out calibration of ``p_correct``
  (:mod:`~vlm_vpr_ros.localization.verification.p_correct`), written as ``verification.json``.
"""

from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.errors import ImageDecodeError, MapError
from vlm_vpr_ros.files.images import decode_image_bytes
from vlm_vpr_ros.localization.verification.components import create_feature, create_matcher
from vlm_vpr_ros.localization.verification.p_correct import (NOISE_MIN_DISTANCE_M, NOISE_PAIRS,
                                                             load_doc, loo_calibration,
                                                             noise_level, noise_pairs, save_doc)
from vlm_vpr_ros.localization.verification.conditions import parse_condition, parse_conditions
from vlm_vpr_ros.localization.verification.evidence import EvidenceConfig
from vlm_vpr_ros.localization.verification.geometry import GeometryConfig, fundamental_inliers
from vlm_vpr_ros.localization.verification.presets import (VerifierPreset, get_preset,
                                                           preset_for_map)
from vlm_vpr_ros.localization.verification.sift import RootSift
from vlm_vpr_ros.localization.verification.stage import Verifier
from vlm_vpr_ros.maps.map_images import SourceImages
from vlm_vpr_ros.maps.reference_map import descriptor_for_map
from vlm_vpr_ros.maps.features import (FeatureStore, attach_features, make_section,
                                       write_submap_features)
from vlm_vpr_ros.threads import one_blas_thread
from vlm_vpr_ros.types import LocalFeatures

log = logging.getLogger(__name__)
#: "none": build a map without local features (answers unverified unless images are given)
NO_FEATURES = ("none", "")
#: leave-one-out queries at build time (bounds the build cost: ~20 matches each)
LOO_QUERIES = 400
#: references queried under each degraded condition (bounds the extra cost: one image decode,
#: one SIFT pass per condition and ~20 matches each)
DEGRADED_QUERIES = 60


class ReferenceExtractor:
    """Global descriptors and local features of reference images (module docstring)."""

    def __init__(self, descriptor: Any, preset: str | None,
                 feature_options: Mapping[str, Any] | None = None,
                 matcher_options: Mapping[str, Any] | None = None) -> None:
        self.descriptor = descriptor
        # not stored in the map (device, threads, weights' paths): the calibration's matches
        # and its degraded queries' features run with them, as the build's did
        self.feature_options = dict(feature_options or {})
        self.matcher_options = dict(matcher_options or {})
        #: query conditions of the verification calibration (None: the default mix)
        self.calibration_conditions: str | Sequence[str] | None = None
        self.preset: VerifierPreset | None = None
        self.extractor = None
        if preset not in NO_FEATURES and preset is not None:
            self.preset = preset_for_map(preset, descriptor.identity())
            self.extractor = create_feature(self.preset.feature,
                                            {**self.preset.feature_config,
                                             **dict(feature_options or {})})
        cfg = self.extractor.config if self.extractor is not None else {}
        vc = getattr(descriptor, "cfg", None)
        self.shared = (self.preset is not None and self.preset.feature == "sift"
                       and hasattr(descriptor, "describe_with_sift") and vc is not None
                       and cfg.get("max_side") == vc.max_side
                       and cfg.get("contrast_threshold") == 0.04
                       and cfg.get("edge_threshold") == 10.0)
        #: a vlad_xfeat map verified with XFeat: one XFeat pass per image serves both
        self.shared_xfeat = (self.preset is not None and self.preset.feature == "xfeat"
                             and hasattr(descriptor, "describe_with_xfeat")
                             and descriptor.xfeat.identity() == self.extractor.identity())

    @property
    def enabled(self) -> bool:
        return self.preset is not None

    def identity(self) -> dict[str, Any]:
        return self.extractor.identity()

    def describe(self, images: Sequence[np.ndarray]
                 ) -> tuple[np.ndarray, list[LocalFeatures] | None]:
        """(n, dim) global descriptors and the local features of each image (None when the
        map stores none)."""
        if not self.enabled:
            return self.descriptor.describe(images), None
        k = self.preset.max_keypoints
        if self.shared:
            out, feats = [], []
            for im in images:
                d, (xy, des, resp, scale, size) = self.descriptor.describe_with_sift(im)
                out.append(d)
                feats.append(RootSift.from_pass(xy, des, resp, size, scale, k))
            return np.stack(out).astype(np.float32), feats
        if self.shared_xfeat:
            pairs = [self.descriptor.describe_with_xfeat(im, k) for im in images]
            return (np.stack([d for d, _ in pairs]).astype(np.float32),
                    [f.head(k) for _, f in pairs])
        return (self.descriptor.describe(images),
                [self.extractor.extract(im, k) for im in images])


def store_features(ref_map: Any, features_of: Callable[[str], LocalFeatures],
                   extractor: ReferenceExtractor) -> None:
    """Write the feature files of the saved map ``ref_map`` (features of each reference id
    from ``features_of``) and list them in its manifest."""
    if ref_map.path is None:
        raise MapError("save the map before storing its local features")
    by_submap = {s.id: _Lazy(list(s.ids), features_of) for s in ref_map.submaps}
    p = extractor.preset
    ref_map.manifest = attach_features(Path(ref_map.path), ref_map.manifest, by_submap,
                                       extractor.identity(), p.name, p.max_keypoints,
                                       p.query_max_keypoints)


class _Lazy(Sequence):
    """Features of a list of ids, produced when indexed (bounded memory for large maps)."""

    def __init__(self, ids: list[str], fn: Callable[[str], LocalFeatures]) -> None:
        self.ids, self.fn = ids, fn

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i):  # type: ignore[override]
        return self.fn(self.ids[i])


def calibrate_map(ref_map: Any, max_queries: int = LOO_QUERIES, top_k: int = 20,
                  progress: bool = False, seed: int = 0,
                  matcher_options: Mapping[str, Any] | None = None,
                  conditions: str | Sequence[str] | None = None,
                  images_dir: str | Path | None = None, descriptor: Any = None,
                  degraded_queries: int | None = None,
                  feature_options: Mapping[str, Any] | None = None) -> dict[str, Any] | None:
    """Leave-one-out calibration of ``p_correct`` on a saved map with stored local features,
    written as its ``verification.json``; None when the map stores no features.
    ``conditions`` (default :data:`~.conditions.DEFAULT_CONDITIONS`): the query conditions;
    those other than ``full`` need the reference images (``images_dir``, else the map's own
    ``images/``, else the folder a ``build-map --images`` map was built from; a map built from
    images has every picture checked against the sizes and sha256 its build recorded:
    :class:`~vlm_vpr_ros.maps.map_images.SourceImages`) and the map's ``descriptor`` (created
    when None); without images only ``full`` is calibrated (a warning). ``degraded_queries``:
    references queried under each degraded condition (default :data:`DEGRADED_QUERIES`).
    ``feature_options`` / ``matcher_options``: settings not stored in the map (a learned
    preset's ``device``, ``threads``, weights' paths), used by every match and by the degraded
    queries' feature extraction."""
    store = FeatureStore.open(Path(ref_map.path), ref_map.manifest)
    if store is None:
        return None
    t0 = time.monotonic()

    preset = get_preset(store.preset or "sift")
    matcher = create_matcher(preset.matcher, {**preset.matcher_config,  # stored features are
                                              **dict(matcher_options or {})})
    geometry = from_mapping(GeometryConfig, preset.geometry, "geometry")  # ... the queries
    owners = [(si, j) for si, s in enumerate(ref_map.submaps) for j in range(s.count)]
    coords = np.concatenate([np.asarray(s.coords) for s in ref_map.submaps])
    starts = np.cumsum([0] + [s.count for s in ref_map.submaps])
    vectors: dict[int, np.ndarray] = {}

    def vec(g: int) -> np.ndarray:
        si, j = owners[g]
        if si not in vectors:
            vectors[si] = np.asarray(ref_map.submaps[si].vectors(), np.float32)
        return vectors[si][j:j + 1]

    everything = list(range(len(ref_map.submaps)))
    copies = photo_copies(vectors.setdefault(si, np.asarray(ref_map.submaps[si].vectors(),
                                                            np.float32))
                          for si in everything)  # read once: vec() serves the queries from it
    extra = max((len(c) for c in copies.values()), default=0)

    def search(g: int, k: int) -> list[tuple[float, int]]:
        found = ref_map.search_submaps(everything, vec(g), k)
        return [(d, int(starts[si] + j)) for d, si, j in found]

    def features_of(g: int) -> LocalFeatures:
        si, j = owners[g]
        return store.get(ref_map.submaps[si].id, j)

    def inliers_of(q: LocalFeatures, refs: Sequence[LocalFeatures]) -> np.ndarray:
        prepared = matcher.prepare(q)
        out = np.zeros(len(refs), np.int64)
        for i, r in enumerate(refs):
            m = matcher.match(prepared, q, r)
            if len(m):
                out[i] = int(fundamental_inliers(q.keypoints[m[:, 0]], r.keypoints[m[:, 1]],
                                                 geometry).sum())
        return out

    conds = [c.name for c in parse_conditions(conditions)]
    degraded, smallest = _degraded_queries(ref_map, conds, images_dir, descriptor, top_k,
                                           extra, dict(feature_options or {}),
                                           dict(matcher_options or {}),
                                           search_vec=lambda v, k: [
                                               (d, int(starts[si] + j)) for d, si, j in
                                               ref_map.search_submaps(everything, v, k)])
    if degraded is None:
        conds = [c for c in conds if c == "full"] or ["full"]
    n_deg = DEGRADED_QUERIES if degraded_queries is None else int(degraded_queries)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(desc="verification calibration", unit="query", disable=None, leave=False)
    with one_blas_thread():
        # the matcher's noise level on unrelated pairs: the competitor floor of the evidence
        t_noise = time.monotonic()
        pairs = noise_pairs(coords, NOISE_PAIRS, NOISE_MIN_DISTANCE_M,
                            np.random.default_rng(seed + 1),
                            copies_of=lambda g: copies.get(g, ()))
        noise = noise_level([int(inliers_of(features_of(i), [features_of(j)])[0])
                             for i, j in pairs])
        noise["seconds"] = round(time.monotonic() - t_noise, 1)
        if not pairs:
            log.warning("%s: no two references %.0f m apart: the %s matcher's noise level is "
                        "not measured (competitor floor %d)", ref_map.path,
                        NOISE_MIN_DISTANCE_M, preset.matcher, noise["floor"])
        cfg = EvidenceConfig(competitor_floor=noise["floor"])
        doc = loo_calibration(coords, search, features_of, inliers_of, top_k,
                              cfg, max_queries, seed,
                              (lambda d, n: bar.update(1)) if bar is not None else None,
                              conds, degraded, n_deg,
                              copies_of=lambda g: copies.get(g, ()))
    if bar is not None:
        bar.close()
    ids = ref_map.all_ids()
    for r in doc["strongest_wrong"]:  # rows change with edits: the references' ids stay
        r["query"], r["answer"] = ids[r.pop("query_row")], ids[r.pop("answer_row")]
    doc["min_long_side_px"] = int(smallest[0]) if smallest else 0
    doc["feature"] = store.feature
    doc["preset"] = store.preset
    doc["noise"] = noise
    save_doc(ref_map, doc)
    loo = doc["loo"]
    log.info("verification calibration: %d leave-one-out queries (%d wrong, %d right) under "
             "%s, %.1f s", loo["queries"], loo["wrong"], loo["right"], ",".join(conds),
             time.monotonic() - t0)
    return doc


def photo_copies(blocks: Iterable[np.ndarray]) -> dict[int, tuple[int, ...]]:
    """Rows (global order over ``blocks``, e.g. the submaps' descriptors) whose global
    descriptors are bit-identical: the same photograph stored more than once, e.g. at a
    look-alike place. {row: the other rows of its group}, only for rows that have copies.
    Exact byte equality: no tolerance that a CPU's rounding could move."""
    groups: dict[bytes, list[int]] = {}
    g = 0
    for block in blocks:
        for row in np.ascontiguousarray(block):
            groups.setdefault(hashlib.sha256(row.tobytes()).digest(), []).append(g)
            g += 1
    return {g: tuple(o for o in rows if o != g)
            for rows in groups.values() if len(rows) > 1 for g in rows}


def calibrated_conditions(ref_map: Any) -> list[str] | None:
    """The query conditions the map's ``verification.json`` was calibrated for (None: none
    recorded, or only a user's results, or a document that does not load: the defaults)."""
    try:
        doc = load_doc(ref_map)
    except MapError as exc:
        log.warning("%s: the earlier verification calibration is unusable (%s): the default "
                    "query conditions are calibrated", ref_map.path, exc)
        return None
    names = [str(c) for c in (doc or {}).get("conditions") or () if c != "user"]
    return names or None


def _degraded_queries(ref_map: Any, conds: Sequence[str], images_dir: str | Path | None,
                      descriptor: Any, top_k: int, extra: int, feature_options: dict,
                      matcher_options: dict, search_vec: Callable
                      ) -> tuple[Callable | None, list[int]]:
    """(``degraded(row)`` for :func:`~.calibration.loo_records`, a one-element list that the
    calls fill with the smallest frame's longer side); (None, []) when no condition needs
    images or the images are not reachable. Each search returns ``top_k`` + 1 + ``extra``
    rows (``extra``: the most copies of one photo, left out with it)."""
    others = [parse_condition(c) for c in conds if c != "full"]
    if not others:
        return None, []
    pictures = SourceImages.for_map(ref_map.path, ref_map.manifest, str(images_dir or ""))
    if pictures.folder is None or not pictures.folder.is_dir():
        log.warning("%s: no reference images reachable: the verification calibration covers "
                    "full-size queries only (conditions %s need the images: "
                    "--reference-images)", ref_map.path, ",".join(c.name for c in others))
        return None, []
    if descriptor is None:
        descriptor = descriptor_for_map(ref_map, None, None)
    verifier = Verifier(ref_map, {"top_k": max(1, top_k)}, feature_options, matcher_options)
    if not verifier.enabled:
        return None, []
    shared = verifier.reuses_sift_of(descriptor)
    shared_xfeat = verifier.reuses_xfeat_of(descriptor)
    k_query = verifier.preset.query_max_keypoints
    ids = ref_map.all_ids()
    smallest: list[int] = []

    def degraded(row: int) -> dict[str, tuple[list[tuple[float, int]], LocalFeatures]]:
        # a map built from images: each picture checked against the size and sha256 the
        # build recorded (a missing or changed one is None, its WARN says why)
        data = pictures.read(ids[row])
        try:
            image = None if data is None else decode_image_bytes(data, ids[row])
        except ImageDecodeError as exc:
            log.warning("calibration query %s skipped: %s", ids[row], exc)
            return {}
        if image is None:
            log.warning("calibration query %s skipped: not readable in %s", ids[row],
                        pictures.folder)
            return {}
        out = {}
        for c in others:
            frame = c.apply(image)
            side = max(frame.shape[:2])
            smallest[:] = [min(smallest[0], side)] if smallest else [side]
            if shared:
                desc, sift_pass = descriptor.describe_with_sift(frame)
                local = verifier.query_features_from_sift(sift_pass)
            elif shared_xfeat:
                desc, local = descriptor.describe_with_xfeat(frame, k_query)
                local = local.head(k_query)
            else:
                desc, local = descriptor.describe_one(frame), verifier.query_features(frame)
            vec = np.asarray(desc, np.float32).reshape(1, -1)
            out[c.name] = (search_vec(vec, top_k + 1 + extra), local)
        return out

    return degraded, smallest


def edit_features(tx: Any, ref_map: Any, gen: int,
                  rewritten: Mapping[str, Sequence[LocalFeatures]],
                  dropped: Sequence[str]) -> None:
    """``map add/remove`` inside its transaction ``tx``: write the feature files of every
    rewritten submap under the generation's names (``<id>.g<gen>``), drop those of emptied
    submaps, and update the manifest's ``local_features`` section in ``tx.new``."""
    sec = tx.new.get("local_features")
    if not sec:
        return
    dtype, dim = np.dtype(sec["feature"]["dtype"]), int(sec["feature"]["descriptor_dim"])
    entries = dict(sec["submaps"])
    for sid in [*rewritten, *dropped]:
        for rel in (entries.get(sid) or {}).get("files", {}).values():
            tx.new["files"].pop(rel, None)
    for sid in dropped:
        entries.pop(sid, None)
    for sid, feats in rewritten.items():
        entries[sid] = write_submap_features(Path(tx.path), f"{sid}.g{gen}", feats, dtype, dim)
        for rel in entries[sid]["files"].values():
            tx.record(rel)
    tx.new["local_features"] = make_section(sec["feature"], sec["preset"],
                                            sec["max_keypoints"], sec["query_max_keypoints"],
                                            entries, tx.new["files"])


def map_extractor(ref_map: Any, descriptor: Any) -> ReferenceExtractor:
    """The extractor of new references for a map with stored features: the map's own preset
    and feature settings (MapError when this software would extract other features)."""
    sec = ref_map.manifest.get("local_features")
    if not sec:
        return ReferenceExtractor(descriptor, None)
    refx = ReferenceExtractor(descriptor, sec.get("preset") or "sift",
                              sec["feature"].get("config") or {})
    refx.preset = replace(refx.preset, max_keypoints=int(sec["max_keypoints"]),
                          query_max_keypoints=int(sec["query_max_keypoints"]))
    mine, stored = refx.identity(), sec["feature"]
    diff = [k for k in ("name", "config", "descriptor_dim", "dtype")
            if mine.get(k) != stored.get(k)]
    if diff:
        raise MapError(f"{ref_map.path}: the map stores {stored.get('name')} features "
                       f"{stored.get('config')}; new references would get {mine.get('config')} "
                       f"(differs in {', '.join(diff)})")
    return refx
