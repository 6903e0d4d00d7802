"""Heavy-tailed error model of a coarse prior (a VLM's (lat, lon) answer) on the sphere.

The model is the areal density of the true position around the prior, as a function of the
great-circle distance only: a mixture of von Mises-Fisher (vMF) components on the sphere — each the
spherical analogue of an isotropic 2-D Gaussian with scale ``sigma_km`` (``kappa = (R/sigma)^2``)
— plus a uniform component over the whole sphere for wild answers. Being densities per km² on the
sphere, they stay correct at every scale, from street level to the antipode.

For a vMF component at angular distance ``t = d / R``::

    density(d) = kappa / (2 pi R^2 (1 - exp(-2 kappa))) * exp(-kappa (1 - cos t))   [per km²]
    P(error <= d) = (1 - exp(-kappa (1 - cos t))) / (1 - exp(-2 kappa))

and the uniform component has density ``1 / (4 pi R^2)`` and ``P(error <= d) = (1 - cos t) / 2``.

Parameters are fitted by EM (:func:`fit_error_model`) from real answers and shipped as JSON
(``vlm_vpr_ros/data/vlm_error_model.json``, see docs/fusion.md) with provenance; the file is
validated at load and a bad file is a :class:`~vlm_vpr_ros.errors.ConfigError` naming the field.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.geodesy import EARTH_RADIUS_KM, MAX_DISTANCE_KM
from vlm_vpr_ros.priors.provider import MAX_PRIOR_SIGMA_KM, MIN_PRIOR_SIGMA_KM

ERROR_MODEL_FORMAT = "vlm_vpr_ros.prior_error_model"
ERROR_MODEL_VERSION = 1
DEFAULT_ERROR_MODEL = Path(__file__).resolve().parents[2] / "data" / "vlm_error_model.json"
_R2 = EARTH_RADIUS_KM ** 2
_LOG_UNIFORM = -math.log(4.0 * math.pi * _R2)


def _kappa(sigma_km: float) -> float:
    return (EARTH_RADIUS_KM / sigma_km) ** 2


def _log_norm(kappa: float) -> float:
    """log of kappa / (2 pi R^2 (1 - exp(-2 kappa)))."""
    return math.log(kappa) - math.log(2.0 * math.pi * _R2) - math.log1p(-math.exp(-2.0 * kappa))


@dataclass(frozen=True)
class ErrorModel:
    """Mixture ``weights[k]`` · vMF(``sigmas_km[k]``) + ``uniform_weight`` · uniform."""

    sigmas_km: tuple[float, ...]
    weights: tuple[float, ...]
    uniform_weight: float
    name: str = "custom"

    def __post_init__(self) -> None:
        if len(self.sigmas_km) != len(self.weights):
            raise ConfigError("error model: sigmas_km and weights differ in length")
        vals = (*self.sigmas_km, *self.weights, self.uniform_weight)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
            raise ConfigError(f"error model {self.name!r}: non-finite parameter")
        # the range of every prior's own sigma (priors.provider.prior_sigma_problem): a scale
        # under 1 cm would overflow kappa = (R / sigma)^2
        if any(not MIN_PRIOR_SIGMA_KM <= s <= MAX_PRIOR_SIGMA_KM for s in self.sigmas_km):
            raise ConfigError(f"error model {self.name!r}: sigmas_km must be in "
                              f"[{MIN_PRIOR_SIGMA_KM:g}, {MAX_PRIOR_SIGMA_KM:.0f}] km")
        if any(w < 0 for w in self.weights) or self.uniform_weight < 0:
            raise ConfigError(f"error model {self.name!r}: negative weight")
        total = sum(self.weights) + self.uniform_weight
        if abs(total - 1.0) > 1e-3:
            raise ConfigError(f"error model {self.name!r}: weights sum to {total:.4f}, not 1")

    # -- construction ---------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any], name: str = "custom") -> "ErrorModel":
        try:
            return cls(tuple(float(s) for s in d["sigmas_km"]),
                       tuple(float(w) for w in d["weights"]), float(d["uniform_weight"]), name)
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"error model {name!r}: needs sigmas_km, weights, uniform_weight "
                              f"({exc!r})") from None

    def as_dict(self) -> dict[str, Any]:
        return {"sigmas_km": [round(s, 6) for s in self.sigmas_km],
                "weights": [round(w, 6) for w in self.weights],
                "uniform_weight": round(self.uniform_weight, 6)}

    @classmethod
    def single(cls, sigma_km: float, uniform_weight: float = 0.01,
               name: str = "provider") -> "ErrorModel":
        """A provider's own scale: one vMF of ``sigma_km`` plus a small uniform floor (a prior
        that claims a precision is still sometimes wild)."""
        return cls((float(sigma_km),), (1.0 - uniform_weight,), uniform_weight, name)

    # -- evaluation -----------------------------------------------------------------------------
    @functools.cached_property
    def _terms(self) -> tuple[tuple[float, float, float], ...]:
        """(kappa, weight · normalisation, log of it) of each vMF component with weight > 0:
        constants of every density evaluation, computed once per model."""
        out = []
        for s, w in zip(self.sigmas_km, self.weights):
            if w > 0:
                k = _kappa(s)
                log_c = math.log(w) + _log_norm(k)
                out.append((k, math.exp(log_c), log_c))
        return tuple(out)

    def log_density(self, d_km: Any) -> np.ndarray:
        """log areal density (per km²) of the true position at great-circle distance(s) d."""
        t = np.asarray(d_km, dtype=np.float64) / EARTH_RADIUS_KM
        one_minus_cos = 2.0 * np.sin(t / 2.0) ** 2
        if self.uniform_weight > 1e-12:  # the uniform floor keeps a linear sum from underflow
            dens = np.full(t.shape, self.uniform_weight * math.exp(_LOG_UNIFORM))
            for k, c, _ in self._terms:
                dens += c * np.exp(-k * one_minus_cos)
            return np.log(dens)
        terms = [np.full(t.shape, math.log(self.uniform_weight) + _LOG_UNIFORM)
                 if self.uniform_weight > 0 else np.full(t.shape, -np.inf)]
        for k, _, log_c in self._terms:
            terms.append(log_c - k * one_minus_cos)
        return np.logaddexp.reduce(np.stack(terms), axis=0)

    def cdf(self, d_km: Any) -> np.ndarray:
        """P(error <= d)."""
        t = np.clip(np.asarray(d_km, dtype=np.float64) / EARTH_RADIUS_KM, 0.0, math.pi)
        one_minus_cos = 2.0 * np.sin(t / 2.0) ** 2
        out = self.uniform_weight * one_minus_cos / 2.0
        for s, w in zip(self.sigmas_km, self.weights):
            k = _kappa(s)
            out = out + w * (-np.expm1(-k * one_minus_cos)) / (-math.expm1(-2.0 * k))
        return np.clip(out, 0.0, 1.0)

    def sample_km(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` error distances drawn from the model (inverse CDF on a fine log grid)."""
        grid = np.concatenate([[0.0], np.logspace(-4, math.log10(MAX_DISTANCE_KM), 4000)])
        cdf = self.cdf(grid)
        return np.interp(rng.uniform(0.0, float(cdf[-1]), n), cdf, grid)

    def quantile(self, p: float) -> float:
        """Distance (km) within which the truth lies with probability ``p`` (bisection)."""
        if not 0.0 < p < 1.0:
            raise ConfigError(f"quantile probability must be in (0, 1), got {p}")
        lo, hi = 0.0, MAX_DISTANCE_KM
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if float(self.cdf(mid)) < p else (lo, mid)
        return hi


# -- fitting ------------------------------------------------------------------------------------
def _solve_kappa(m: float, kappa_max: float) -> float:
    """kappa maximizing the weighted vMF likelihood given mean (1 - cos t) = m."""
    if m <= 0:
        return kappa_max
    lo, hi = math.log(1e-6), math.log(kappa_max)

    def g(logk: float) -> float:  # 1/k - 2/(e^{2k}-1) - m, decreasing in k
        k = math.exp(logk)
        tail = 2.0 / math.expm1(2.0 * k) if k < 300 else 0.0
        return 1.0 / k - tail - m

    if g(hi) > 0:
        return kappa_max
    if g(lo) < 0:
        return math.exp(lo)
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(mid) > 0 else (lo, mid)
    return math.exp(0.5 * (lo + hi))


def fit_error_model(errors_km: Sequence[float], init_sigmas_km: Sequence[float] = (1, 15, 150,
                    1500), min_sigma_km: float = 0.1, iters: int = 500,
                    name: str = "fitted") -> tuple[ErrorModel, float]:
    """EM fit of the mixture to observed prior errors (km); returns (model, mean log-lik).

    ``min_sigma_km`` is the resolution floor: no component may be narrower (see
    docs/fusion.md: errors under the floor are treated as hits at the floor's scale, so the
    prior never out-votes visual evidence among candidates a few km apart)."""
    d = np.asarray([e for e in errors_km if e is not None and math.isfinite(e)], np.float64)
    if len(d) < 10:
        raise ConfigError(f"need at least 10 errors to fit an error model, got {len(d)}")
    t = np.clip(d / EARTH_RADIUS_KM, 0.0, math.pi)
    omc = 2.0 * np.sin(t / 2.0) ** 2
    kappa_max = _kappa(min_sigma_km)
    kappas = [min(_kappa(max(s, min_sigma_km)), kappa_max) for s in init_sigmas_km]
    k_n = len(kappas)
    w = np.full(k_n + 1, 1.0 / (k_n + 1))
    ll_prev = -np.inf
    for _ in range(iters):
        logp = np.stack([np.full_like(omc, _LOG_UNIFORM)]
                        + [_log_norm(k) - k * omc for k in kappas])
        logp += np.log(np.maximum(w, 1e-300))[:, None]
        lse = np.logaddexp.reduce(logp, axis=0)
        ll = float(lse.mean())
        resp = np.exp(logp - lse)
        w = resp.mean(axis=1)
        for j in range(k_n):
            r = resp[j + 1]
            if r.sum() > 1e-9:
                kappas[j] = _solve_kappa(float((r * omc).sum() / r.sum()), kappa_max)
        if ll - ll_prev < 1e-10:
            break
        ll_prev = ll
    order = np.argsort([-k for k in kappas])  # narrow to wide
    sig = tuple(float(EARTH_RADIUS_KM / math.sqrt(kappas[j])) for j in order)
    wts = tuple(float(w[j + 1]) for j in order)
    model = ErrorModel(sig, wts, float(1.0 - sum(wts)), name)
    return model, ll_prev


# -- the shipped file ---------------------------------------------------------------------------
@dataclass(frozen=True)
class ErrorModelSet:
    """The models of one error-model file: ``default`` plus named ones (per VLM)."""

    models: dict[str, ErrorModel]
    default: str
    provenance: dict[str, Any]
    path: str

    def get(self, name: str | None = None) -> ErrorModel:
        key = name or self.default
        if key not in self.models:
            raise ConfigError(f"unknown error model {key!r} in {self.path}; choices: "
                              f"{', '.join(sorted(self.models))}")
        return self.models[key]

    def for_source(self, source: str) -> ErrorModel:
        """The model fitted for a prior's source (``openai:gpt-4o`` → ``gpt-4o``), else the
        default one."""
        tail = source.split(":", 1)[-1]
        return self.models.get(tail) or self.models[self.default]


def load_error_models(path: str | Path | None = None) -> ErrorModelSet:
    """Read and validate an error-model JSON; any problem is a ConfigError naming the file."""
    path = Path(path) if path else DEFAULT_ERROR_MODEL
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read error model file {path}: {exc.strerror}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"error model file {path} is not valid JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"error model file {path}: not a JSON object")
    if doc.get("format") != ERROR_MODEL_FORMAT or doc.get("version") != ERROR_MODEL_VERSION:
        raise ConfigError(f"error model file {path}: format/version must be "
                          f"{ERROR_MODEL_FORMAT!r}/{ERROR_MODEL_VERSION}, got "
                          f"{doc.get('format')!r}/{doc.get('version')!r}")
    raw = doc.get("models")
    if not isinstance(raw, dict) or not raw:
        raise ConfigError(f"error model file {path}: 'models' must be a non-empty object")
    models = {}
    for name, entry in raw.items():
        if not isinstance(entry, dict):
            raise ConfigError(f"error model file {path}: models.{name} is not an object")
        try:
            models[name] = ErrorModel.from_dict(entry, name)
        except ConfigError as exc:
            raise ConfigError(f"error model file {path}: {exc}") from None
    default = doc.get("default")
    if default not in models:
        raise ConfigError(f"error model file {path}: default {default!r} is not one of "
                          f"{', '.join(sorted(models))}")
    return ErrorModelSet(models, default, dict(doc.get("provenance") or {}), str(path))
