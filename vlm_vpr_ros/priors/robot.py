"""The robot's own estimate as a prior (``prior_topic``): pure core, no ROS.

A robot almost always knows roughly where it is: its last good GNSS fix or its filter's pose,
with a covariance. The node converts such messages (``msg_adapters/robot_prior.py``) into a
:class:`RobotEstimate` (position, 1-sigma from the covariance, stamp) and hands it to
:meth:`TopicPrior.update`, which checks it (:func:`check_estimate`) and keeps the latest good
one. A query then gets it as a :class:`~vlm_vpr_ros.priors.provider.Prior` whose ``sigma_km`` is

    sigma(age) = sigma_0 + growth_m_per_s * age

(the error of dead reckoning grows about linearly with time since the last absolute
position), ``age`` measured from the estimate's stamp on the node's clock. An estimate older
than ``max_age_s`` is *stale*: not used. Its sigma passes the one check of every prior's sigma
(:func:`~vlm_vpr_ros.priors.provider.prior_sigma_problem`, docs/priors.md) with a tighter top:
an estimate whose sigma, as sent or grown with age, is above ``MAX_PRIOR_SIGMA_M`` (1000 km) is
*too uncertain*: not used, like a stale one (never clamped: a clamped sigma would be a lie),
and a sigma under 1 cm (no source is more precise) is raised to 1 cm. The prior provider the
node also has (the VLM, a fixed hint, ...) is the fallback, in the order ``order`` says:

* ``topic_first``: the robot's estimate while it is fresh, else the provider;
* ``provider_first``: the provider, and the robot's estimate when the provider gives none
  (failed, timed out, refused).

The prior carries its own sigma, so ``trust_operator_prior`` may let it resolve fixes
(docs/verification.md); the guard against a prior whose sigma is a lie is in the status rule
(``status.prior_consistent``), not here.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import math
import re
import threading
import time
from dataclasses import dataclass
from typing import Callable

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.geodesy import valid_latlon
from vlm_vpr_ros.priors.provider import (MIN_PRIOR_SIGMA_KM, Prior, PriorProvider, PriorQuery,
                                         PriorResult)

log = logging.getLogger(__name__)
ORDERS = ("topic_first", "provider_first")
TOO_UNCERTAIN = "too uncertain"
#: a sigma above this (m) is no prior worth the name (an uninitialised filter says 1e9); inside
#: every prior's range (provider.MAX_PRIOR_SIGMA_KM, half the Earth's circumference)
MAX_PRIOR_SIGMA_M = 1.0e6


@dataclass(frozen=True)
class RobotEstimate:
    """One position estimate of the robot (WGS-84) with its own 1-sigma."""

    lat: float
    lon: float
    sigma_m: float  # 1-sigma horizontal error (m), from the message's covariance
    stamp_s: float  # the message's stamp, seconds on the node's clock
    source: str  # "navsat", "pose" or "odometry" (and the topic), for answers and logs


@dataclass(frozen=True)
class TopicPriorConfig:
    growth_m_per_s: float = 1.0
    max_age_s: float = 120.0
    max_future_s: float = 1.0  # stamps further ahead of the node's clock are refused
    order: str = "topic_first"

    def __post_init__(self) -> None:
        if self.order not in ORDERS:
            raise ConfigError(f"prior_order {self.order!r}; choices: {', '.join(ORDERS)}")
        for name in ("growth_m_per_s", "max_future_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"prior topic {name} must be >= 0, got {v}")
        if not (math.isfinite(self.max_age_s) and self.max_age_s > 0):
            raise ConfigError(f"prior topic max_age_s must be > 0, got {self.max_age_s}")
        horizon = self.usable_s(0.0)
        if horizon < self.max_age_s:
            log.warning("prior topic: with growth %g m/s an estimate's sigma passes %g km "
                        "after at most %.0f s, before max_age_s %g s: older ones are refused "
                        "as too uncertain", self.growth_m_per_s, MAX_PRIOR_SIGMA_M / 1000.0,
                        horizon, self.max_age_s)

    def usable_s(self, sigma_m: float) -> float:
        """How long (s) an estimate of ``sigma_m`` stays usable: until it is stale or its
        grown sigma passes ``MAX_PRIOR_SIGMA_M``, whichever comes first."""
        if self.growth_m_per_s <= 0:
            return self.max_age_s
        return min(self.max_age_s, (MAX_PRIOR_SIGMA_M - sigma_m) / self.growth_m_per_s)


def sigma_from_covariance(cxx: float, cxy: float, cyy: float) -> float:
    """1-sigma (m) of a horizontal 2x2 covariance: the square root of its larger eigenvalue
    (conservative for an elongated ellipse). ConfigError for NaN, zero, negative or
    non-positive-definite covariance: such a message says nothing about its error."""
    if not all(math.isfinite(v) for v in (cxx, cxy, cyy)):
        raise ConfigError("covariance is not finite (NaN or inf)")
    if cxx <= 0 or cyy <= 0 or cxx * cyy - cxy * cxy <= 0:
        raise ConfigError(f"covariance is not positive definite (xx {cxx:g}, yy {cyy:g}, "
                          f"xy {cxy:g}): zero or negative variance")
    half_tr, det = (cxx + cyy) / 2.0, cxx * cyy - cxy * cxy
    return math.sqrt(half_tr + math.sqrt(max(half_tr * half_tr - det, 0.0)))


def check_estimate(est: RobotEstimate, now_s: float, cfg: TopicPriorConfig) -> str:
    """Why ``est`` must be ignored ("" when it may be used)."""
    if not valid_latlon(est.lat, est.lon):
        return f"position ({est.lat}, {est.lon}) is not a valid WGS-84 position"
    if not (math.isfinite(est.sigma_m) and 0 < est.sigma_m <= MAX_PRIOR_SIGMA_M):
        return f"sigma {est.sigma_m:g} m is not in (0, {MAX_PRIOR_SIGMA_M:g}]"
    if not math.isfinite(est.stamp_s):
        return "stamp is not finite"
    if est.stamp_s > now_s + cfg.max_future_s:
        return (f"stamp {est.stamp_s - now_s:.1f} s in the future (node clock; more than "
                f"{cfg.max_future_s:g} s)")
    if now_s - est.stamp_s > cfg.max_age_s:
        return (f"stamp {now_s - est.stamp_s:.1f} s old, older than max_age_s "
                f"{cfg.max_age_s:g} s")
    return ""


def grown_sigma_m(est: RobotEstimate, now_s: float, growth_m_per_s: float) -> float:
    """The estimate's sigma grown with its age (module docstring)."""
    return est.sigma_m + growth_m_per_s * max(0.0, now_s - est.stamp_s)


def _with_topic_reason(res: PriorResult, own: PriorResult) -> PriorResult:
    """The provider's failure, saying also that the robot's estimate was refused as too
    uncertain (an answer without a prior must not hide that the robot had one)."""
    if not own.reason.startswith(TOO_UNCERTAIN):
        return res
    return PriorResult(None, res.source, f"{res.reason}; topic: {own.reason}", res.latency_s,
                       res.raw_text, res.extra)


def _kind(why: str) -> str:
    """The kind of a problem: its text without the numbers (one WARN per kind)."""
    return re.sub(r"\(?[-+]?(?:\d[\d.e+-]*|nan|inf)\)?", "#", why)


class TopicPrior(PriorProvider):
    """Prior provider fed with the robot's own estimates; ``fallback`` answers when it has
    none (or first, with ``provider_first``). Thread-safe: ``update`` comes from a ROS
    callback, ``request`` from the query worker."""

    name = "topic"

    def __init__(self, fallback: PriorProvider, config: TopicPriorConfig = TopicPriorConfig(),
                 clock: Callable[[], float] = time.time, label: str = "topic") -> None:
        self.fallback, self.config, self._clock, self.label = fallback, config, clock, label
        self._lock = threading.Lock()
        self._latest: RobotEstimate | None = None
        self._warned: set[str] = set()
        self.rejected = 0  # estimates ignored (counted; one WARN per kind of problem)
        self.used = 0  # queries answered with the robot's estimate

    def update(self, est: RobotEstimate) -> str:
        """Keep ``est`` as the latest estimate; returns why it was ignored ("" if kept)."""
        why = check_estimate(est, self._clock(), self.config)
        with self._lock:
            if why:
                self.rejected += 1
                kind = _kind(why)
                if kind not in self._warned:
                    self._warned.add(kind)
                    log.warning("prior topic %s: ignoring an estimate from %s: %s (further ones "
                                "like it are counted, not logged)", self.label, est.source, why)
                return why
            if self._latest is None or est.stamp_s >= self._latest.stamp_s:
                self._latest = est
            self._warned.clear()  # the next problem after a good estimate is worth a WARN
        return ""

    def reject(self, source: str, why: str) -> None:
        """A message that could not even be converted (bad covariance, unknown frame)."""
        with self._lock:
            self.rejected += 1
            kind = _kind(why)
            if kind not in self._warned:
                self._warned.add(kind)
                log.warning("prior topic %s: ignoring a message from %s: %s (further ones like "
                            "it are counted, not logged)", self.label, source, why)

    def current(self) -> tuple[Prior | None, str]:
        """The robot's estimate as a prior now, or (None, why not)."""
        now = self._clock()
        with self._lock:
            est = self._latest
        if est is None:
            return None, "no_estimate"
        age = now - est.stamp_s
        if age > self.config.max_age_s:
            return None, f"stale ({age:.0f} s old)"
        sigma = grown_sigma_m(est, now, self.config.growth_m_per_s)
        if sigma > MAX_PRIOR_SIGMA_M:
            return None, (f"{TOO_UNCERTAIN} (sigma grown to {sigma / 1000.0:.0f} km in "
                          f"{age:.0f} s, more than {MAX_PRIOR_SIGMA_M / 1000.0:g} km)")
        sigma_km = max(sigma / 1000.0, MIN_PRIOR_SIGMA_KM)  # the floor of every prior's sigma
        return Prior(est.lat, est.lon, f"{self.name}:{est.source}", sigma_km), ""

    def _own(self) -> PriorResult:
        prior, why = self.current()
        if prior is None:
            return PriorResult.failure(self.name, why)
        self.used += 1
        return PriorResult(prior, self.name, extra={"sigma_m": prior.sigma_km * 1000.0})

    def request(self, query: PriorQuery) -> "cf.Future[PriorResult]":
        first = None
        if self.config.order == "topic_first":
            first = self._own()
            if first.ok:
                fut: cf.Future[PriorResult] = cf.Future()
                fut.set_result(first)
                return fut
            if not first.reason.startswith(TOO_UNCERTAIN):
                return self.fallback.request(query)
        out: cf.Future[PriorResult] = cf.Future()
        inner = self.fallback.request(query)

        def done(f: "cf.Future[PriorResult]") -> None:
            try:
                res = f.result()
            except BaseException as exc:  # noqa: BLE001 - includes CancelledError
                res = PriorResult.failure(self.fallback.name, f"error: {exc!r}")
            if not res.ok:
                own = first or self._own()
                res = own if own.ok else _with_topic_reason(res, own)
            if not out.done():
                out.set_result(res)

        inner.add_done_callback(done)
        out.add_done_callback(lambda f: inner.cancel() if f.cancelled() else None)
        return out

    def close(self) -> None:
        self.fallback.close()
