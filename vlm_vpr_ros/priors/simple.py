"""Prior providers that need no network: ``none``, ``fixed`` and ``recorded``."""

from __future__ import annotations

import logging
import os

from vlm_vpr_ros.errors import DataError, PriorError
from vlm_vpr_ros.files.csvio import read_rows, strict_float, unique_rows
from vlm_vpr_ros.geodesy import valid_latlon
from vlm_vpr_ros.priors.provider import (KeyedTable, Prior, PriorProvider, PriorQuery,
                                         PriorResult, prior_sigma_problem)

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
            why = prior_sigma_problem(sigma_km)
            if why:
                raise PriorError(f"fixed prior option sigma_km={sigma_km}: {why}")
            sigma_km = float(sigma_km)
        self.prior = Prior(lat, lon, self.name, sigma_km)

    def _compute(self, query: PriorQuery) -> PriorResult:
        return PriorResult(self.prior, self.name)


def read_prior_csv(path: str | os.PathLike[str]) -> dict[str, tuple[float, float]]:
    """Read a ``file, lat, lon`` CSV into {file: (lat, lon)}; blank/invalid rows and (0, 0)
    placeholders are skipped (counted in a warning); a file repeated with other coordinates is
    a DataError. (:func:`read_prior_table` also reads the optional ``sigma_m`` column.)"""
    return {k: (v[0], v[1]) for k, v in read_prior_table(path).items()}


def read_prior_table(path: str | os.PathLike[str]
                     ) -> dict[str, tuple[float, float, float | None]]:
    """``file, lat, lon[, sigma_m]`` CSV into {file: (lat, lon, sigma_km or None)}.

    ``sigma_m`` (optional column): the prior's own 1-sigma error in metres, e.g. a robot's
    filter estimate ("I was here, +-300 m"); it has the meaning of the ``topic`` prior's σ
    (docs/priors.md), so a recorded robot prior may be trusted for fixes like an operator's
    hint (``trust_operator_prior``). A blank cell: no σ of its own (the source's fitted error
    model). A ``sigma_m`` outside the range of every prior's sigma (1 cm to half the Earth's
    circumference: :func:`~vlm_vpr_ros.priors.provider.prior_sigma_problem`), or not a
    number, is a DataError naming the file, line and field: never a prior with a made-up σ,
    and never a run whose every query fails later."""
    items = []
    bad = 0
    cols, rows = read_rows(path, "priors CSV", ("file", "lat", "lon"))
    has_sigma = "sigma_m" in cols
    for n, row in rows:
        lat, lon = strict_float(row["lat"]), strict_float(row["lon"])  # no "3_9", no "nan"
        sigma_km = None
        text = (row.get("sigma_m") or "").strip() if has_sigma else ""
        if text:
            sigma_m = strict_float(text)
            why = (prior_sigma_problem(sigma_m / 1000.0, "m") if sigma_m is not None
                   else f"{text!r} is not a number")
            if why:
                raise DataError(f"priors CSV {path}:{n}: field sigma_m: {why}")
            sigma_km = sigma_m / 1000.0
        if lat is None or lon is None:
            bad += 1
            continue
        if valid_latlon(lat, lon) and (lat, lon) != (0.0, 0.0):  # (0, 0): a placeholder
            items.append((n, row["file"], (lat, lon, sigma_km)))
        else:
            bad += 1
    if bad:
        log.warning("%s: %d row(s) without a valid lat/lon (or at 0, 0) are treated as "
                    "'no prior'", path, bad)
    return unique_rows(items, path, "file")


class RecordedPrior(PriorProvider):
    """Priors recorded beforehand, looked up by the query's file name (``key``); a
    ``sigma_m`` column gives each its own σ (:func:`read_prior_table`)."""

    name = "recorded"

    def __init__(self, path: str) -> None:
        self.path = path
        self.table = read_prior_table(path)
        self._lookup = KeyedTable(self.table)

    def _compute(self, query: PriorQuery) -> PriorResult:
        if not query.key:
            return PriorResult.failure(self.name, "no_key")
        hit, why = self._lookup.find(query.key)
        if hit is None:
            return PriorResult.failure(self.name, why)
        return PriorResult(Prior(hit[0], hit[1], self.name, hit[2]), self.name)
