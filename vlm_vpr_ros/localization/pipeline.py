"""Image → hypothesis: the descriptor stored with a map plus the localizer, in one object."""

from __future__ import annotations

import logging
import os
import time
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.descriptors import GlobalDescriptor
from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
from vlm_vpr_ros.maps.reference_map import ReferenceMap, descriptor_for_map
from vlm_vpr_ros.priors.base import PriorResult
from vlm_vpr_ros.types import Hypothesis

log = logging.getLogger(__name__)


def _same_state(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


class LocalizationPipeline:
    """Bundle of map, descriptor and localizer used by the CLI, the node and the evaluators."""

    def __init__(self, ref_map: ReferenceMap, descriptor: GlobalDescriptor,
                 localizer: Localizer,
                 descriptor_config: Mapping[str, Any] | None = None) -> None:
        self.map = ref_map
        self.descriptor = descriptor
        self.localizer = localizer
        self.descriptor_config = dict(descriptor_config or {})
        self.verify = False  # sha256 pass when the map is (re)read: set by open()

    @classmethod
    def open(cls, map_dir: str | os.PathLike[str], descriptor: str | None = None,
             localizer: LocalizerConfig | Mapping[str, Any] | None = None,
             descriptor_config: Mapping[str, Any] | None = None,
             verify: bool = False) -> "LocalizationPipeline":
        """``verify``: also check every file's sha256 (otherwise the manifest and file sizes
        are checked; ``vlm-vpr map verify`` does the full pass offline)."""
        ref_map = ReferenceMap.load(map_dir, verify=verify)
        desc = descriptor_for_map(ref_map, descriptor, descriptor_config)
        if not isinstance(localizer, LocalizerConfig):
            localizer = from_mapping(LocalizerConfig, localizer, "localizer")
        pipeline = cls(ref_map, desc, Localizer(ref_map, localizer), descriptor_config)
        pipeline.verify = bool(verify)
        return pipeline

    def reloaded(self, verify: bool | None = None) -> "LocalizationPipeline":
        """A new pipeline on the map re-read from the same folder (e.g. after ``vlm-vpr map
        add``), with the same localizer settings. The descriptor object is reused when the
        map's descriptor identity and state are unchanged (no model reload). MapError when the
        folder no longer holds a valid map of a comparable descriptor; ``self`` is untouched.
        ``verify``: sha256 pass (default: as when this pipeline was opened; a full pass over a
        4.1M-reference map reads 4.5 GB)."""
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
        new = LocalizationPipeline(ref_map, desc, Localizer(ref_map, self.localizer.config),
                                   self.descriptor_config)
        new.verify = verify
        return new

    def describe(self, image: np.ndarray) -> np.ndarray:
        return self.descriptor.describe_one(image)

    def localize_descriptor(self, desc: np.ndarray,
                            prior_result: PriorResult | None = None) -> Hypothesis:
        return self.localizer.localize(desc, prior_result)

    def localize_image(self, image: np.ndarray,
                       prior_result: PriorResult | None = None) -> Hypothesis:
        t0 = time.perf_counter()
        desc = self.describe(image)
        t1 = time.perf_counter()
        hyp = self.localize_descriptor(desc, prior_result)
        hyp.timings_ms["descriptor_ms"] = (t1 - t0) * 1e3
        return hyp
