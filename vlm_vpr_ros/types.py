"""Result types of the localization core."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from vlm_vpr_ros.priors.base import Prior, PriorResult


@dataclass(frozen=True)
class Candidate:
    """One retrieved reference."""

    ref_id: str
    lat: float
    lon: float
    l2_sq: float  # squared L2 descriptor distance to the query
    submap: str
    prior_km: float | None = None  # haversine distance to the prior (None without prior)
    posterior: float | None = None  # posterior weight after fusion (docs/fusion.md)


@dataclass
class Hypothesis:
    """The answer to "where am I?" for one query."""

    lat: float
    lon: float
    ref_id: str
    submap: str  # chosen submap id(s), "+"-joined; "*" for the global set
    uncertainty_m: float  # calibrated radius holding the truth with 68 % probability (m)
    candidates: list[Candidate] = field(default_factory=list)
    prior: Prior | None = None
    prior_result: PriorResult | None = None
    flags: tuple[str, ...] = ()
    timings_ms: dict[str, float] = field(default_factory=dict)
    radius95_m: float = math.nan  # calibrated 95 % radius (m); NaN: not computed
    confidence: float = math.nan  # posterior mass within the vote radius of the estimate
    fusion: str = ""  # fusion mode that produced the hypothesis ("posterior" / "paper")

    @property
    def flagged(self) -> bool:
        """True when the hypothesis is a fallback (no prior, prior failed, ...)."""
        return bool(set(self.flags) & FALLBACK_FLAGS)

    def as_row(self) -> dict[str, Any]:
        """Flat dict for results CSVs."""
        p = self.prior
        pr = self.prior_result
        return {
            "lat": f"{self.lat:.7f}",
            "lon": f"{self.lon:.7f}",
            "prior_lat": "" if p is None else f"{p.lat:.6f}",
            "prior_lon": "" if p is None else f"{p.lon:.6f}",
            "prior_source": (p.source if p else (pr.source if pr else "none")),
            "prior_reason": "" if pr is None else pr.reason,
            # how a VLM answer was read: structured, text, text_fallback ("" for no answer)
            "prior_parse": "" if pr is None else str(pr.extra.get("parse_path") or ""),
            "submap": self.submap,
            "ref_id": self.ref_id,
            "uncertainty_m": f"{self.uncertainty_m:.1f}",
            "radius95_m": "" if math.isnan(self.radius95_m) else f"{self.radius95_m:.1f}",
            "confidence": "" if math.isnan(self.confidence) else f"{self.confidence:.4f}",
            "fusion": self.fusion,
            "n_candidates": len(self.candidates),
            "flags": "|".join(self.flags),
        }


#: flags that mark a hypothesis as a fallback rather than the full method
FALLBACK_FLAGS = frozenset({
    "no_prior", "prior_failed", "prior_not_in_map", "prior_far_from_match", "no_match",
})
