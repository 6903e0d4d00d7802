"""The verification stage: after retrieval and fusion, verify the top K candidates with local
features and geometry, re-rank them by the verified evidence and compute ``p_correct`` and the
radii of the answer (docs/verification.md).

Reference features come from the map's feature store (:mod:`vlm_vpr_ros.maps.features`), else
from the reference images (the map's own ``images/`` folder, or ``images_dir``) extracted on
demand and cached; without either the answers are flagged ``unverified``. A feature store that
is damaged or of another feature type is a MapError at open when verification is ``required``,
else a warning and unverified answers — never a fix from wrong data.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.errors import ConfigError, DescriptorError, ImageDecodeError, MapError
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.localization.verification.components import (LocalFeatureExtractor, Matcher,
                                                              create_feature, create_matcher)
from vlm_vpr_ros.localization.verification.conditions import ConditionWatch
from vlm_vpr_ros.localization.verification.status import horizontal_sigma, k_risk
from vlm_vpr_ros.localization.verification.p_correct import (PCorrect, load_doc,
                                                             support_spread_m, verified_radius)
from vlm_vpr_ros.localization.verification.evidence import EvidenceConfig, spread_radii, weigh
from vlm_vpr_ros.localization.verification.geometry import GeometryConfig, fundamental_inliers
from vlm_vpr_ros.localization.verification.presets import check_map_preset, preset_for_map
from vlm_vpr_ros.localization.verification.share import map_shared, resolve_threads
from vlm_vpr_ros.maps.features import FeatureStore
from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.maps.map_images import images_folder
from vlm_vpr_ros.threads import one_blas_thread
from vlm_vpr_ros.types import Hypothesis, LocalFeatures

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VerificationConfig:
    top_k: int = 20  # candidates verified per query (0 = off)
    required: bool = False  # a missing / damaged feature store is an error at open
    images_dir: str = ""  # reference images for maps without stored features
    cache_size: int = 256  # reference features extracted from images, kept in memory
    #: threads sharing a query's candidates (0 = auto: the usable cores, at most 4); the
    #: answers do not depend on it (verification/share.py)
    threads: int = 0
    #: local-feature / matcher settings that are not part of the map (learned weights' paths,
    #: device), e.g. {"weights": "/data/disk/depth-save.pth"}
    feature_options: Mapping[str, Any] = field(default_factory=dict)
    matcher_options: Mapping[str, Any] = field(default_factory=dict)
    #: the preset the caller expects ("" = the map's own); another than the map's (features
    #: and calibration) is a ConfigError naming both (presets.check_map_preset)
    preset: str = ""

    def __post_init__(self) -> None:
        if not (0 <= self.top_k <= 1000 and self.cache_size >= 0):
            raise ConfigError(f"verify_top_k must be in 0..1000, got {self.top_k}")
        if not 0 <= self.threads <= 64:
            raise ConfigError(f"verify_threads must be in 0..64 (0 = auto), got {self.threads}")


def _same_feature(a: dict, b: dict) -> list[str]:
    return [k for k in ("name", "config", "descriptor_dim", "dtype") if a.get(k) != b.get(k)]


class Verifier:
    """Verifies the candidates of a hypothesis against one map (module docstring)."""

    def __init__(self, ref_map: Any, config: VerificationConfig | dict | None = None,
                 feature_options: dict | None = None, matcher_options: dict | None = None
                 ) -> None:
        if not isinstance(config, VerificationConfig):
            config = from_mapping(VerificationConfig, config, "verification")
        self.map, self.config = ref_map, config
        self.threads = resolve_threads(config.threads)
        self.store: FeatureStore | None = None
        self.unavailable = ""  # why answers are unverified ("" = verification runs)
        self.images_root: Path | None = None
        self.extractor: LocalFeatureExtractor | None = None
        self.matcher: Matcher | None = None
        self.model = PCorrect(np.zeros(0))
        self.watch: ConditionWatch | None = None  # frames below the calibrated conditions
        self._cache: collections.OrderedDict[str, LocalFeatures | None] = \
            collections.OrderedDict()
        self._lock = threading.Lock()
        if config.top_k == 0:
            self.unavailable = "verification off (verify_top_k 0)"
            return
        root = Path(ref_map.path) if ref_map.path is not None else None
        self.images_root = self._images_root(root)  # also for drawing (--save-matches)
        try:
            self.store = FeatureStore.open(root, ref_map.manifest) if root else None
        except MapError as exc:
            if config.required:
                raise
            log.warning("%s; answers are unverified", exc)
            self.unavailable = f"feature store unusable: {exc}"
            return
        if self.store is not None:
            self.preset = preset_for_map(self.store.preset or "sift", None)
            feat = self.store.feature
            self.preset = replace(self.preset, feature=feat["name"],
                                  feature_config=feat.get("config", {}),
                                  max_keypoints=self.store.max_keypoints,
                                  query_max_keypoints=self.store.query_max_keypoints)
        else:
            if self.images_root is None or not self.images_root.is_dir():
                msg = ("the map stores no local features and no reference images folder is "
                       "reachable (give images_dir / --reference-images)")
                if self.images_root is not None:
                    msg += f"; {self.images_root} is gone"
                if config.required:
                    raise MapError(f"{root}: {msg}")
                log.warning("%s: %s; answers are unverified", root, msg)
                self.unavailable = msg
                return
            self.preset = preset_for_map("sift", ref_map.descriptor_identity)
            log.info("%s stores no local features: verifying against the images in %s",
                     root, self.images_root)
        fopts = {**config.feature_options, **dict(feature_options or {})}
        mopts = {**config.matcher_options, **dict(matcher_options or {})}
        try:
            self._build(fopts, mopts)
        except (MapError, ConfigError, DescriptorError) as exc:
            if isinstance(exc, ConfigError) and (fopts or mopts or config.preset):
                raise  # the user's options do not fit the map's features: say so, at once
            msg = f"{root}: local features unusable: {exc}"
            if config.required:
                raise MapError(msg) from None
            log.warning("%s; answers are unverified", msg)
            self.unavailable = msg

    def _build(self, feature_options: dict, matcher_options: dict) -> None:
        p = self.preset
        self.extractor = create_feature(p.feature, {**p.feature_config, **feature_options})
        self.matcher = create_matcher(p.matcher, {**p.matcher_config, **matcher_options})
        self.geometry = from_mapping(GeometryConfig, p.geometry, "geometry")
        if self.store is not None:
            diff = _same_feature(self.store.feature, self.extractor.identity())
            if diff:
                raise MapError(f"{self.map.path}: stored local features are "
                               f"{self.store.feature} but the query side would use "
                               f"{self.extractor.identity()} (differs in {', '.join(diff)})")
            built = self.store.feature.get("weights_sha256")
            now = self.extractor.identity().get("weights_sha256")
            if built and now and built != now:  # another descriptor space: no calibration
                raise MapError(f"{self.map.path}: the map's {p.feature} features were "
                               f"extracted with another checkpoint (sha256 {built[:12]}..., "
                               f"now {now[:12]}...): rebuild the map or use its checkpoint")
        doc = load_doc(self.map)
        check_map_preset(str(self.map.path), self.config.preset,
                         self.store.preset if self.store is not None else "sift",
                         (doc or {}).get("preset"))
        if doc is not None and doc.get("feature") not in (None, self.extractor.identity()) \
                and _same_feature(doc["feature"], self.extractor.identity()):
            log.warning("%s: the verification calibration was made with other local "
                        "features; p_correct is uncalibrated", self.map.path)
            doc = None
        self.model = PCorrect.from_doc(self._usable_calibration(doc))
        if self.model.calibrated and not self.model.conditions:
            log.warning("%s: the verification calibration predates query conditions (full-size "
                        "references only): answers are flagged uncalibrated_conditions; "
                        "recalibrate with 'vlm-vpr calibrate --map MAP --conditions ...'",
                        self.map.path)
        self.watch = ConditionWatch(str(self.map.path), self.model.min_long_side_px,
                                    self.model.conditions)
        self.evidence = EvidenceConfig(
            place_radius_m=float((doc or {}).get("place_radius_m", 25.0)),
            competitor_floor=int((doc or {}).get("competitor_floor", 12)))

    def _usable_calibration(self, doc: dict | None) -> dict | None:
        """``doc``, or None when ``top_k`` is below the K it was calibrated with: fewer verified
        candidates leave out look-alike competitors, so the inlier ratio rises and the bound
        ``p_correct >= level`` on wrong answers no longer holds (more candidates only lower
        the ratio: the bound stays conservative)."""
        k_cal = int((doc or {}).get("top_k", 0))
        if doc is not None and self.config.top_k < k_cal:
            log.warning("%s: verify_top_k %d is below the %d candidates the map's p_correct was "
                        "calibrated with: p_correct is uncalibrated (no STATUS_FIX)",
                        self.map.path, self.config.top_k, k_cal)
            return None
        return doc

    def _images_root(self, root: Path | None) -> Path | None:
        d = images_folder(root, self.map.manifest, self.config.images_dir)
        if self.config.images_dir and not d.is_dir():
            raise ConfigError(f"reference images folder {d} does not exist")
        return d

    # -- properties ------------------------------------------------------------------------
    @property
    def enabled(self) -> bool:
        return not self.unavailable

    @property
    def calibration_source(self) -> str:
        return self.model.source

    def reuses_sift_of(self, descriptor: Any) -> bool:
        """Whether the query features are the SIFT pass of this VLAD ``descriptor``."""
        if not self.enabled or self.preset.feature != "sift" or \
                not hasattr(descriptor, "describe_with_sift"):
            return False
        cfg = self.extractor.config
        vc = descriptor.cfg
        return (cfg.get("max_side") == vc.max_side and cfg.get("contrast_threshold") == 0.04
                and cfg.get("edge_threshold") == 10.0
                and self.preset.query_max_keypoints <= vc.n_features)

    def reuses_xfeat_of(self, descriptor: Any) -> bool:
        """Whether the query features are the XFeat pass of this ``vlad_xfeat`` descriptor
        (the same extractor identity: weights and frame size)."""
        if not self.enabled or self.preset.feature != "xfeat" or \
                not hasattr(descriptor, "describe_with_xfeat"):
            return False
        return descriptor.xfeat.identity() == self.extractor.identity()

    # -- features ----------------------------------------------------------------------------
    def query_features(self, image: np.ndarray) -> LocalFeatures:
        return self.extractor.extract(image, self.preset.query_max_keypoints)

    def query_features_from_sift(self, sift_pass: tuple) -> LocalFeatures:
        from vlm_vpr_ros.localization.verification.sift import RootSift

        xy, des, resp, scale, size = sift_pass
        return RootSift.from_pass(xy, des, resp, size, scale, self.preset.query_max_keypoints)

    def reference_features(self, candidates: Sequence[Any]) -> list[LocalFeatures | None]:
        if self.store is not None:
            return [self.store.get(c.submap, c.row) if c.row >= 0 else None
                    for c in candidates]
        return [self._from_image(c.ref_id) for c in candidates]

    def _from_image(self, ref_id: str) -> LocalFeatures | None:
        from vlm_vpr_ros.files.images import load_image

        with self._lock:
            if ref_id in self._cache:
                self._cache.move_to_end(ref_id)
                return self._cache[ref_id]
        try:
            f: LocalFeatures | None = self.extractor.extract(
                load_image(self.images_root / ref_id), self.preset.max_keypoints)
        except (ImageDecodeError, OSError) as exc:
            log.warning("reference %s cannot be verified: %s", ref_id, exc)
            f = None
        with self._lock:
            self._cache[ref_id] = f
            while len(self._cache) > self.config.cache_size:
                self._cache.popitem(last=False)
        return f

    def inliers(self, query: LocalFeatures, refs: Sequence[LocalFeatures | None]
                ) -> tuple[np.ndarray, list[np.ndarray]]:
        """Inlier counts (-1 where a reference has no features) and the inlier matches; the
        candidates are shared between ``threads`` threads (:mod:`.share`: same answers)."""
        prepared = self.matcher.prepare(query)

        def one(i: int) -> tuple[int, np.ndarray]:
            r = refs[i]
            if r is None:
                return -1, np.zeros((0, 2), np.int64)
            with one_blas_thread():  # on the thread that runs it: a setting may be per thread
                m = self.matcher.match(prepared, query, r)
            mask = fundamental_inliers(query.keypoints[m[:, 0]], r.keypoints[m[:, 1]],
                                       self.geometry) if len(m) else np.zeros(0, bool)
            return int(mask.sum()), m[mask]

        done = map_shared(one, len(refs), self.threads if self.matcher.shares_threads else 1)
        return np.array([c for c, _ in done], np.int64), [m for _, m in done]

    # -- the stage ---------------------------------------------------------------------------
    def to_verify(self, candidates: Sequence[Any]) -> list[Any]:
        """The top K in posterior order, then those of the top K in visual order (squared
        descriptor distance) not among them: with a prior, the look-alikes the prior pushed
        down stay competitors, so the evidence depends on the prior only through the explicit
        gate (without a prior both orders hold the same candidates)."""
        k = self.config.top_k
        top = list(candidates[:k])
        seen = {id(c) for c in top}
        visual = sorted(candidates, key=lambda c: c.l2_sq)[:k]
        return top + [c for c in visual if id(c) not in seen]

    def verify(self, hyp: Hypothesis, query: LocalFeatures | None, error_model: Any = None,
               trust_prior: bool = False, level: float = 0.95,
               radii_calibrated: bool = True,
               weigh_prior: Callable[[Hypothesis], None] | None = None) -> None:
        """Verify ``hyp``'s top K candidates in place (module docstring); the inlier matches
        of the re-ranked top K are kept in ``hyp.matches`` (for drawing). ``radii_calibrated``:
        whether the posterior's radii are calibrated on this map (else an answer that geometry
        does not support gets the candidates' spread as its radii). ``weigh_prior``: sets
        ``p_correct`` of the ranked answer from a trusted prior with its own sigma
        (:mod:`.prior_trust`) before the radii and the protection level are derived from it."""
        if not self.enabled or query is None or not hyp.candidates:
            why = self.unavailable or ("no query features" if query is None else "no match")
            hyp.verification = f"unverified: {why}"
            hyp.flags = tuple(hyp.flags) + ("unverified",)
            return
        t0 = time.perf_counter()
        top = self.to_verify(hyp.candidates)
        counts, matches = self.inliers(query, self.reference_features(top))
        lat = np.array([c.lat for c in top])
        lon = np.array([c.lon for c in top])
        logp = None
        if hyp.prior is not None and error_model is not None:
            g = np.atleast_1d(haversine_km(hyp.prior.lat, hyp.prior.lon, lat, lon))
            logp = np.asarray(error_model.log_density(g), np.float64)
        ev = weigh(lat, lon, counts, logp, self.evidence)
        old = top[0]
        ranked = [replace(top[i], inliers=int(counts[i])) for i in ev.order]
        seen = {id(c) for c in top}
        hyp.candidates = ranked + [c for c in hyp.candidates if id(c) not in seen]
        best = ranked[0]
        p = self.model.p_correct(ev.score)
        pu = self.model.p_correct(ev.score_ungated)
        hyp.p_correct, hyp.p_correct_without_prior = p, pu
        hyp.inliers, hyp.inlier_ratio = ev.winner_inliers, ev.score
        shift_m = float(haversine_km(old.lat, old.lon, best.lat, best.lon)) * 1000.0
        hyp.lat, hyp.lon, hyp.ref_id = best.lat, best.lon, best.ref_id
        if weigh_prior is not None:
            weigh_prior(hyp)
            p = hyp.p_correct
        p_radius = p if trust_prior else pu  # an untrusted prior narrows no radius
        fb68 = hyp.uncertainty_m + shift_m
        fb95 = (hyp.radius95_m if math.isfinite(hyp.radius95_m) else fb68) + shift_m
        if ev.winner_inliers <= self.evidence.competitor_floor and (
                not radii_calibrated or int(counts.max()) <= 0):
            # geometry supports no candidate (a lens cap, fog, a place not in the map) and the
            # posterior's radii are not calibrated on this map (no leave-one-out pairs, e.g.
            # the demo map: its posterior said 25 m for a black frame), or not one candidate
            # has a single inlier (a 32x32 frame: no evidence at all, whatever the posterior's
            # floor says; a map with one picture twice at one place has "calibrated" 25 m
            # radii): the radii cover the candidates' spread instead
            s68, s95 = spread_radii(lat, lon, ev.winner)
            fb68, fb95 = max(fb68, s68), max(fb95, s95)
        r68 = verified_radius(self.model, p_radius, 0.68, fb68, level)
        hyp.uncertainty_m = r68
        hyp.radius95_m = max(r68, verified_radius(self.model, p_radius, 0.95, fb95, level))
        support = counts
        if trust_prior and logp is not None:  # a trusted prior rules out the gated look-alikes
            gated = logp < logp[ev.winner] - math.log(self.evidence.prior_gate)
            support = np.where(gated, -1, counts)
        hyp.protection_m = self._protection(hyp, lat, lon, support, ev.winner, p_radius, level)
        hyp.verification = "verified"
        hyp.flags = tuple(hyp.flags) + ("verified",) + self._condition_flags(query)
        hyp.matches = [matches[i] for i in ev.order]
        hyp.timings_ms["verify_ms"] = (time.perf_counter() - t0) * 1e3

    def _protection(self, hyp: Hypothesis, lat: np.ndarray, lon: np.ndarray,
                    counts: np.ndarray, winner: int, p: float, level: float) -> float:
        """The protection level (m) of a verified answer (docs/verification.md section 3):
        for an answer verified at ``p_correct >= level`` the support spread (how far apart the
        references that verify with substantial inliers are; with a trusted prior, not those
        the prior gate rules out) plus the calibrated residual; for any other the larger of that
        and the 1 - integrity_risk radius of its own Gaussian (its radii); NaN on an
        uncalibrated map (no integrity claim)."""
        m = self.model
        if not m.calibrated:
            return math.nan
        pl = support_spread_m(lat, lon, counts, winner, self.evidence.competitor_floor) \
            + m.residual_m
        if math.isfinite(p) and p >= level:
            return pl
        return max(pl, k_risk(m.integrity_risk) * horizontal_sigma(hyp))

    def _condition_flags(self, query: LocalFeatures) -> tuple[str, ...]:
        """``uncalibrated_conditions`` on a map calibrated before query conditions existed, or
        for a frame smaller than the calibration covered (warned once)."""
        if not self.model.calibrated:
            return ()
        if not self.model.conditions:
            return ("uncalibrated_conditions",)
        w, h = query.size
        shape = (round(h * query.scale), round(w * query.scale))
        if self.watch is not None and self.watch.check(shape):
            return ("uncalibrated_conditions",)
        return ()


def widen_to_candidate_spread(hyp: Hypothesis, k: int = 20) -> None:
    """Radii of an unverified answer on a map whose posterior radii are not calibrated (no
    leave-one-out pairs, e.g. the demo map): at least the spread of its top ``k`` candidates
    around it. Nothing tells the answer from its look-alikes there, so its own radius (a 25 m
    floor for a black frame) would claim a certainty nobody measured."""
    top = list(hyp.candidates[:k])
    if not top or not (math.isfinite(hyp.lat) and math.isfinite(hyp.lon)):
        return
    lat, lon, ids = [c.lat for c in top], [c.lon for c in top], [c.ref_id for c in top]
    if hyp.ref_id in ids:
        winner = ids.index(hyp.ref_id)
    else:
        lat, lon, winner = lat + [hyp.lat], lon + [hyp.lon], len(top)
    s68, s95 = spread_radii(np.array(lat), np.array(lon), winner)
    r68 = hyp.uncertainty_m if math.isfinite(hyp.uncertainty_m) else 0.0
    r95 = hyp.radius95_m if math.isfinite(hyp.radius95_m) else r68
    hyp.uncertainty_m = max(r68, s68)
    hyp.radius95_m = max(r95, s95, hyp.uncertainty_m)
