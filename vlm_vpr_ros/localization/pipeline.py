"""Image → hypothesis: the descriptor stored with a map, the localizer and the verification
stage, in one object; every answer leaves with its status (docs/verification.md)."""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field, replace
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.descriptors import GlobalDescriptor
from vlm_vpr_ros.errors import MapError, VlmVprError
from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
from vlm_vpr_ros.localization.verification.stage import (VerificationConfig, Verifier,
                                                         widen_to_candidate_spread)
from vlm_vpr_ros.localization.verification import prior_trust
from vlm_vpr_ros.localization.verification.status import StatusPolicy, stamp_status
from vlm_vpr_ros.maps.reference_map import ReferenceMap, descriptor_for_map
from vlm_vpr_ros.priors.provider import PriorResult
from vlm_vpr_ros.threads import one_blas_thread
from vlm_vpr_ros.types import Hypothesis, LocalFeatures

log = logging.getLogger(__name__)


def _same_state(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@dataclass
class QueryDescription:
    """What a query image gives before retrieval: its global descriptor and, when the map is
    verified, its local features (from the same SIFT pass on vlad_rootsift maps)."""

    desc: np.ndarray
    local: LocalFeatures | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)


def verify_and_stamp(hyp: Hypothesis, local: LocalFeatures | None, verifier: Verifier | None,
                     localizer: Localizer, policy: StatusPolicy) -> Hypothesis:
    """Verify ``hyp`` with the query's ``local`` features (when there is a verifier), then stamp
    its status under ``policy``."""
    calibrated = not localizer.calibration_source.startswith("none")
    if verifier is not None and hyp.candidates:
        model = localizer.error_model_for(hyp.prior) if hyp.prior is not None else None
        def weigh(h: Hypothesis) -> None:  # a prior with its own sigma: weight + guard
            if prior_trust.applies(h, policy):
                prior_trust.weigh_trusted_prior(h, evidence=verifier.evidence)

        verifier.verify(hyp, local, model, trust_prior=policy.trusts(hyp),
                        level=policy.fix_min_p_correct, radii_calibrated=calibrated,
                        weigh_prior=weigh)
    elif "unverified" not in hyp.flags:
        hyp.flags = tuple(hyp.flags) + ("unverified",)
        hyp.verification = hyp.verification or "unverified: verification off"
    if not calibrated and "unverified" in hyp.flags:
        widen_to_candidate_spread(hyp)  # e.g. a lens cap with verify_top_k 0: not 25 m
    return stamp_status(hyp, policy)


class LocalizationPipeline:
    """Bundle of map, descriptor, localizer and verifier used by the CLI, the node and the
    evaluators."""

    def __init__(self, ref_map: ReferenceMap, descriptor: GlobalDescriptor,
                 localizer: Localizer,
                 descriptor_config: Mapping[str, Any] | None = None,
                 verifier: Verifier | None = None, status: StatusPolicy | None = None) -> None:
        self.map = ref_map
        self.descriptor = descriptor
        self.localizer = localizer
        self.descriptor_config = dict(descriptor_config or {})
        self.verifier = verifier
        self.status_policy = status or StatusPolicy()
        self.verify = False  # sha256 pass when the map is (re)read: set by open()
        self._refused_top_k: int | None = None  # a verify_top_k that could not be applied

    @classmethod
    def open(cls, map_dir: str | os.PathLike[str], descriptor: str | None = None,
             localizer: LocalizerConfig | Mapping[str, Any] | None = None,
             descriptor_config: Mapping[str, Any] | None = None,
             verify: bool = False,
             verification: VerificationConfig | Mapping[str, Any] | None = None,
             status: StatusPolicy | None = None) -> "LocalizationPipeline":
        """``verify``: also check every file's sha256 (otherwise the manifest and file sizes
        are checked; ``vlm-vpr map verify`` does the full pass offline). ``verification``:
        :class:`VerificationConfig` (``top_k`` 20 by default; 0 turns it off)."""
        ref_map = ReferenceMap.load(map_dir, verify=verify)
        desc = descriptor_for_map(ref_map, descriptor, descriptor_config)
        if not isinstance(localizer, LocalizerConfig):
            localizer = from_mapping(LocalizerConfig, localizer, "localizer")
        if not isinstance(verification, VerificationConfig):
            verification = from_mapping(VerificationConfig, verification, "verification")
        pipeline = cls(ref_map, desc, Localizer(ref_map, localizer), descriptor_config,
                       Verifier(ref_map, verification), status)
        pipeline.verify = bool(verify)
        return pipeline

    def reloaded(self, verify: bool | None = None) -> "LocalizationPipeline":
        """A new pipeline on the map re-read from the same folder (e.g. after ``vlm-vpr map
        add``), with the same localizer, verification and status settings. The descriptor
        object is reused when the map's descriptor identity and state are unchanged (no model
        reload). MapError when the folder no longer holds a valid map of a comparable
        descriptor; ``self`` is untouched. ``verify``: sha256 pass (default: as when this
        pipeline was opened; a full pass over a 4.1M-reference map reads 4.5 GB)."""
        if self.map.path is None:
            raise MapError("this pipeline's map was not loaded from a folder; nothing to reload")
        verify = self.verify if verify is None else bool(verify)
        ref_map = ReferenceMap.load(self.map.path, verify=verify)
        same = (ref_map.descriptor_identity == self.map.descriptor_identity
                and _same_state(ref_map.descriptor_state, self.map.descriptor_state))
        if same:
            desc = self.descriptor
        else:
            desc = descriptor_for_map(ref_map, self.descriptor.name, self.descriptor_config)
            log.warning("map %s now has another descriptor state or identity: descriptor "
                        "recreated", ref_map.path)
        vcfg = self.verifier.config if self.verifier is not None else VerificationConfig(0)
        new = LocalizationPipeline(ref_map, desc, Localizer(ref_map, self.localizer.config),
                                   self.descriptor_config, Verifier(ref_map, vcfg),
                                   self.status_policy)
        new.verify = verify
        return new

    def tune(self, status: StatusPolicy | None = None, verify_top_k: int | None = None) -> None:
        """Runtime tuning (the node's writable parameters), for the next query: the status
        policy, and how many candidates are verified (a new verifier on the same map)."""
        if status is not None:
            self.status_policy = status
        v = self.verifier
        if verify_top_k is not None and v is not None and v.config.top_k != verify_top_k \
                and verify_top_k != self._refused_top_k:
            try:
                self.verifier = Verifier(self.map, replace(v.config, top_k=int(verify_top_k)))
            except VlmVprError as exc:  # e.g. verification_required on a map without features
                self._refused_top_k = verify_top_k  # said once, not at every query
                log.error("verify_top_k %d cannot be applied, keeping %d: %s", verify_top_k,
                          v.config.top_k, exc)

    def describe(self, image: np.ndarray) -> np.ndarray:
        return self.descriptor.describe_one(image)

    def describe_query(self, image: np.ndarray) -> QueryDescription:
        """Global descriptor and (when verifying) local features of one query image; BLAS on
        this thread (:mod:`vlm_vpr_ros.threads`)."""
        with one_blas_thread():
            return self._describe_query(image)

    def _describe_query(self, image: np.ndarray) -> QueryDescription:
        t0 = time.perf_counter()
        v = self.verifier
        if v is not None and v.reuses_sift_of(self.descriptor):
            desc, sift_pass = self.descriptor.describe_with_sift(image)
            local = v.query_features_from_sift(sift_pass)
            return QueryDescription(desc, local, {"descriptor_ms":
                                                  (time.perf_counter() - t0) * 1e3})
        if v is not None and v.reuses_xfeat_of(self.descriptor):  # one XFeat pass for both
            k = v.preset.query_max_keypoints
            desc, xfeat_pass = self.descriptor.describe_with_xfeat(image, k)
            return QueryDescription(desc, xfeat_pass.head(k), {
                "descriptor_ms": (time.perf_counter() - t0) * 1e3})
        desc = self.describe(image)
        t1 = time.perf_counter()
        local = v.query_features(image) if v is not None and v.enabled else None
        t2 = time.perf_counter()
        times = {"descriptor_ms": (t1 - t0) * 1e3}
        if local is not None:
            times["local_features_ms"] = (t2 - t1) * 1e3
        return QueryDescription(desc, local, times)

    def localize_descriptor(self, desc: np.ndarray,
                            prior_result: PriorResult | None = None,
                            local: LocalFeatures | None = None) -> Hypothesis:
        """Retrieval + fusion, then verification with the query's ``local`` features (without
        them the answer is flagged ``unverified``), then the status."""
        with one_blas_thread():
            hyp = self.localizer.localize(desc, prior_result)
            return self.finish(hyp, local)

    def finish(self, hyp: Hypothesis, local: LocalFeatures | None) -> Hypothesis:
        """Verification (when configured) and the status of a localized hypothesis."""
        return verify_and_stamp(hyp, local, self.verifier, self.localizer, self.status_policy)

    def localize_image(self, image: np.ndarray,
                       prior_result: PriorResult | None = None) -> Hypothesis:
        q = self.describe_query(image)
        hyp = self.localize_descriptor(q.desc, prior_result, q.local)
        hyp.timings_ms.update(q.timings_ms)
        return hyp
