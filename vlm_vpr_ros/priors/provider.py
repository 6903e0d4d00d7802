"""The prior-source interface: something that guesses a coarse (lat, lon) for a query image.

Providers are asynchronous by contract: :meth:`PriorProvider.request` returns a
``concurrent.futures.Future`` immediately and never blocks the caller. Failures (timeouts, HTTP
errors, refusals, unreadable text) are *values* — a :class:`PriorResult` with ``prior=None`` and a
``reason`` — never exceptions, so a robot keeps localizing (flagged) when the VLM is down.
"""

from __future__ import annotations

import abc
import concurrent.futures as cf
import math
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vlm_vpr_ros.geodesy import MAX_DISTANCE_KM
from vlm_vpr_ros.redact import redact

#: the range of a prior's own 1-sigma (km), checked wherever a prior enters (a priors CSV's
#: ``sigma_m``, the ``fixed`` provider's ``sigma_km``, the robot's estimate grown with age):
#: above, the prior error model's own range (a scale of at most half the Earth's circumference);
#: below, 1 cm: no position source is more precise, and far narrower scales overflow the
#: model's concentration (R / sigma)^2 (docs/priors.md)
MIN_PRIOR_SIGMA_KM = 1.0e-5
MAX_PRIOR_SIGMA_KM = MAX_DISTANCE_KM


def prior_sigma_problem(sigma_km: float, unit: str = "km") -> str:
    """Why ``sigma_km`` cannot be a prior's own 1-sigma ("" when it can): the one check of a
    prior's sigma; callers name where it came from (file:line, option, topic). ``unit``
    ("km" or "m"): the unit the message speaks, the one the user wrote."""
    scale = {"km": 1.0, "m": 1000.0}[unit]
    try:
        s = float(sigma_km)
    except (TypeError, ValueError):
        return f"{sigma_km!r} is not a number"
    if math.isfinite(s) and MIN_PRIOR_SIGMA_KM <= s <= MAX_PRIOR_SIGMA_KM:
        return ""
    return (f"{s * scale:g} {unit} is outside [{MIN_PRIOR_SIGMA_KM * scale:g}, "
            f"{MAX_PRIOR_SIGMA_KM * scale:.0f}] {unit} (1 cm to half the Earth's "
            "circumference, the prior error model's range)")


@dataclass(frozen=True)
class Prior:
    """A coarse position guess in WGS-84 degrees."""

    lat: float
    lon: float
    source: str  # provider name, e.g. "openai:gpt-4o", "fixed", "recorded"
    #: the provider's own error scale (km, 1-sigma of a 2-D Gaussian-like error) when it has
    #: one; None: the fusion uses the fitted VLM error model of the source (docs/fusion.md)
    sigma_km: float | None = None


@dataclass(frozen=True)
class PriorQuery:
    """What a provider may use to answer: pixels, the encoded file, and a lookup key."""

    image: np.ndarray | None = None  # (H, W, 3) uint8 RGB
    encoded: bytes | None = None  # original JPEG/PNG bytes when available
    key: str | None = None  # file name (recorded answers) or frame id


@dataclass(frozen=True)
class PriorResult:
    """Outcome of one prior request. ``prior is None`` means "no prior" and ``reason`` says why."""

    prior: Prior | None
    source: str
    reason: str = ""  # "" when ok; e.g. "timeout", "http_429", "refusal", "no_coordinates"
    latency_s: float = 0.0
    raw_text: str | None = None  # the VLM's raw answer, for audit (never contains secrets)
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # reasons go to results CSVs, /diagnostics and relocalize answers, and may hold the
        # text of an exception (a URL with userinfo, a header echoed by an endpoint)
        if self.reason:
            object.__setattr__(self, "reason", redact(self.reason))

    @property
    def ok(self) -> bool:
        return self.prior is not None

    @classmethod
    def failure(cls, source: str, reason: str, latency_s: float = 0.0,
                raw_text: str | None = None) -> "PriorResult":
        return cls(prior=None, source=source, reason=reason, latency_s=latency_s,
                   raw_text=raw_text)


class PriorProvider(abc.ABC):
    """Base class of prior sources. Subclasses implement :meth:`_compute` (blocking) or override
    :meth:`request` for natively asynchronous clients."""

    name: str = ""

    def request(self, query: PriorQuery) -> "cf.Future[PriorResult]":
        """Start a request and return a future; cheap providers complete it synchronously."""
        fut: cf.Future[PriorResult] = cf.Future()
        t0 = time.monotonic()
        try:
            result = self._compute(query)
        except Exception as exc:  # noqa: BLE001 - a provider bug must not kill the caller
            result = PriorResult.failure(self.name, f"error: {exc}")
        if not result.latency_s:
            result = PriorResult(result.prior, result.source, result.reason,
                                 time.monotonic() - t0, result.raw_text, result.extra)
        fut.set_result(result)
        return fut

    def get(self, query: PriorQuery, timeout_s: float | None = None) -> PriorResult:
        """Blocking convenience: wait for :meth:`request` at most ``timeout_s`` seconds."""
        return wait_prior(self.request(query), self.name, timeout_s)

    def _compute(self, query: PriorQuery) -> PriorResult:  # pragma: no cover - abstract-ish
        raise NotImplementedError

    def close(self) -> None:
        """Cancel pending work and free resources."""


def wait_prior(fut: "cf.Future[PriorResult]", source: str,
               timeout_s: float | None) -> PriorResult:
    """Wait for a prior future at most ``timeout_s`` seconds; a timeout cancels the request and
    becomes a ``timeout`` failure value."""
    try:
        return fut.result(timeout=timeout_s)
    except cf.TimeoutError:
        fut.cancel()
        return PriorResult.failure(source, "timeout", latency_s=timeout_s or 0.0)


class KeyedTable:
    """Recorded values looked up by a query's key: the exact key, else its file name alone
    ('images/a.jpg' and 'a.jpg' both work) when exactly one recorded key has that name; a name
    shared by several recorded keys is ambiguous (reason ``ambiguous_key``), never one of them
    picked silently."""

    def __init__(self, table: dict[str, Any]) -> None:
        self.table = table
        self._by_name: dict[str, list[str]] = {}
        for k in table:
            self._by_name.setdefault(os.path.basename(k), []).append(k)

    def find(self, key: str) -> tuple[Any, str]:
        """(value, "") or (None, reason: not_recorded / ambiguous_key)."""
        if key in self.table:
            return self.table[key], ""
        keys = self._by_name.get(os.path.basename(key), [])
        if len(keys) > 1:
            return None, "ambiguous_key"
        return (self.table[keys[0]], "") if keys else (None, "not_recorded")
