"""Prior providers that need no network: ``none``, ``fixed`` and ``recorded``."""

from __future__ import annotations

import logging
import math
import os

from vlm_vpr_ros.errors import PriorError
from vlm_vpr_ros.files.csvio import read_rows, strict_float, unique_rows
from vlm_vpr_ros.geodesy import valid_latlon
from vlm_vpr_ros.priors.provider import KeyedTable, Prior, PriorProvider, PriorQuery, PriorResult

log = logging.getLogger(__name__)


class NoPrior(PriorProvider):
    """Never gives a prior: the localizer falls back to flagged global retrieval."""

    name = "none"

    def _compute(self, query: PriorQuery) -> PriorResult:
        return PriorResult.failure(self.name, "disabled")


class FixedPrior(PriorProvider):
    """An operator's hint: the same (lat, lon) for every query."""

    name = "fixed"

    def __init__(self, lat: float, lon: float, sigma_km: float | None = None) -> None:
        lat, lon = float(lat), float(lon)
        if not valid_latlon(lat, lon):
            raise PriorError(f"fixed prior ({lat}, {lon}) is not a valid WGS-84 position")
        if sigma_km is not None:
            sigma_km = float(sigma_km)
            if not (math.isfinite(sigma_km) and sigma_km > 0):
                raise PriorError(f"fixed prior sigma_km must be > 0, got {sigma_km}")
        self.prior = Prior(lat, lon, self.name, sigma_km)

    def _compute(self, query: PriorQuery) -> PriorResult:
        return PriorResult(self.prior, self.name)


def read_prior_csv(path: str | os.PathLike[str]) -> dict[str, tuple[float, float]]:
    """Read a ``file, lat, lon`` CSV into {file: (lat, lon)}; blank/invalid rows and (0, 0)
    placeholders are skipped (counted in a warning); a file repeated with other coordinates is
    a DataError."""
    items = []
    bad = 0
    for n, row in read_rows(path, "priors CSV", ("file", "lat", "lon"))[1]:
        lat, lon = strict_float(row["lat"]), strict_float(row["lon"])  # no "3_9", no "nan"
        if lat is None or lon is None:
            bad += 1
            continue
        if valid_latlon(lat, lon) and (lat, lon) != (0.0, 0.0):  # (0, 0): a placeholder
            items.append((n, row["file"], (lat, lon)))
        else:
            bad += 1
    if bad:
        log.warning("%s: %d row(s) without a valid lat/lon (or at 0, 0) are treated as 'no "
                    "prior'", path, bad)
    return unique_rows(items, path, "file")


class RecordedPrior(PriorProvider):
    """Priors recorded beforehand, looked up by the query's file name (``key``)."""

    name = "recorded"

    def __init__(self, path: str) -> None:
        self.path = path
        self.table = read_prior_csv(path)
        self._lookup = KeyedTable(self.table)

    def _compute(self, query: PriorQuery) -> PriorResult:
        if not query.key:
            return PriorResult.failure(self.name, "no_key")
        hit, why = self._lookup.find(query.key)
        if hit is None:
            return PriorResult.failure(self.name, why)
        return PriorResult(Prior(hit[0], hit[1], self.name), self.name)
