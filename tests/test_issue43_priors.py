"""Issue 43: one check of a prior's sigma wherever a prior enters (a priors CSV's ``sigma_m``,
the ``fixed`` provider's ``sigma_km``, the robot's estimate grown with age); no sigma outside
the error model's range reaches it."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from vlm_vpr_ros.errors import ConfigError, DataError, PriorError
from vlm_vpr_ros.geodesy import MAX_DISTANCE_KM
from vlm_vpr_ros.localization.fusion.error_model import ErrorModel
from vlm_vpr_ros.priors import create_prior_provider
from vlm_vpr_ros.priors.provider import (MAX_PRIOR_SIGMA_KM, MIN_PRIOR_SIGMA_KM, Prior,
                                         PriorProvider, PriorQuery, PriorResult,
                                         prior_sigma_problem)
from vlm_vpr_ros.priors.robot import (MAX_PRIOR_SIGMA_M, RobotEstimate, TopicPrior,
                                      TopicPriorConfig)
from vlm_vpr_ros.priors.simple import RecordedPrior

INSIDE = [MIN_PRIOR_SIGMA_KM, 0.001, 5.0, 1000.0, MAX_PRIOR_SIGMA_KM]
OUTSIDE = [1e-300, 0.0, -5.0, MIN_PRIOR_SIGMA_KM / 2, MAX_PRIOR_SIGMA_KM * 1.001, 3e4, 1e9,
           math.nan, math.inf]


def test_the_range_is_the_error_models_own():
    assert MAX_PRIOR_SIGMA_KM == MAX_DISTANCE_KM
    for s in INSIDE:  # every accepted sigma gives a model whose densities are finite
        assert prior_sigma_problem(s) == ""
        m = ErrorModel.single(s)
        d = np.array([0.0, s, 10 * s, MAX_DISTANCE_KM])
        assert np.all(np.isfinite(m.log_density(d))) and np.all(np.isfinite(m.cdf(d)))
    for s in OUTSIDE:
        assert "is outside" in prior_sigma_problem(s), s
    assert "not a number" in prior_sigma_problem("abc")
    assert "0 m is outside [0.01, 20015114] m" in prior_sigma_problem(0.0, "m")  # the user's unit


def test_the_error_model_refuses_what_the_check_refuses():
    for s in OUTSIDE:  # never an OverflowError (1e-300 was one on every query)
        with pytest.raises(ConfigError, match=r"sigmas_km must be in \[1e-05, 20015\]|non-fin"):
            ErrorModel.single(s)


@pytest.mark.parametrize("sigma", ["1e-300", "30000", "0", "-1", "nan", "inf"])
def test_fixed_sigma_km_outside_the_range_names_the_option(sigma):
    with pytest.raises(PriorError, match=f"option sigma_km={sigma}: .* is outside"):
        create_prior_provider("fixed", {"lat": 48.85, "lon": 2.35, "sigma_km": sigma})
    ok = create_prior_provider("fixed", {"lat": 48.85, "lon": 2.35, "sigma_km": "20015"})
    assert ok.get(PriorQuery()).prior.sigma_km == 20015.0


@pytest.mark.parametrize("cell", ["1e-300", "3e7", "1e12", "0", "-5", "nan", "abc"])
def test_priors_csv_sigma_outside_the_range_names_file_line_and_field(tmp_path, cell):
    csv = tmp_path / "p.csv"
    csv.write_text(f"file,lat,lon,sigma_m\na.jpg,37.7,-122.4,100\nb.jpg,37.8,-122.5,{cell}\n")
    with pytest.raises(DataError) as exc:
        RecordedPrior(str(csv))
    assert f"{csv}:3: field sigma_m" in str(exc.value)


def test_priors_csv_at_the_bounds_is_accepted(tmp_path):
    csv = tmp_path / "p.csv"
    csv.write_text("file,lat,lon,sigma_m\na.jpg,37.7,-122.4,0.01\nb.jpg,37.8,-122.5,2e7\n"
                   "c.jpg,37.8,-122.5,\n")
    table = RecordedPrior(str(csv)).table
    assert table["a.jpg"][2] == pytest.approx(1e-5) and table["b.jpg"][2] == 2e4
    assert table["c.jpg"][2] is None


class Clock:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class Fallback(PriorProvider):
    name = "vlm"

    def _compute(self, query):
        return PriorResult(Prior(48.0, 2.0, self.name), self.name)


def test_a_grown_sigma_past_the_maximum_is_refused_not_clamped(caplog):
    clock = Clock(100_000.0)
    with caplog.at_level(logging.WARNING, logger="vlm_vpr_ros.priors.robot"):
        cfg = TopicPriorConfig(growth_m_per_s=1000.0, max_age_s=86_400.0)
    assert "refused as too uncertain" in caplog.text  # said once, at configuration
    assert cfg.usable_s(0.0) == pytest.approx(MAX_PRIOR_SIGMA_M / 1000.0)
    p = TopicPrior(Fallback(), cfg, clock)
    assert p.update(RobotEstimate(37.77, -122.42, 30.0, clock.t - 100.0, "navsat")) == ""
    prior, why = p.current()  # 100 s: 100 km, used
    assert why == "" and prior.sigma_km == pytest.approx(100.03)
    clock.t += 29_900.0  # 30,000 s old: 30,000 km, more than any prior's range
    prior, why = p.current()
    assert prior is None and why.startswith("too uncertain") and "30000 km" in why
    res = p.request(PriorQuery()).result(timeout=5)
    assert res.ok and res.prior.source == "vlm"  # the fallback answers, no failed query


def test_a_tiny_robot_sigma_is_raised_to_the_floor():
    clock = Clock(1000.0)
    p = TopicPrior(Fallback(), TopicPriorConfig(growth_m_per_s=0.0), clock)
    assert p.update(RobotEstimate(37.77, -122.42, 1e-9, 1000.0, "pose")) == ""
    prior, _ = p.current()
    assert prior.sigma_km == MIN_PRIOR_SIGMA_KM


def test_config_stays_strict():
    with pytest.raises(ConfigError):
        TopicPriorConfig(growth_m_per_s=math.inf)


class NoneProvider(PriorProvider):
    name = "none"

    def _compute(self, query):
        return PriorResult.failure(self.name, "disabled")


@pytest.mark.parametrize("order", ["topic_first", "provider_first"])
def test_an_answer_without_a_prior_says_the_robots_was_too_uncertain(order):
    clock = Clock(100_000.0)
    p = TopicPrior(NoneProvider(), TopicPriorConfig(growth_m_per_s=1000.0, max_age_s=86_400.0,
                                                    order=order), clock)
    p.update(RobotEstimate(37.77, -122.42, 30.0, clock.t - 1.0, "navsat"))
    clock.t += 29_999.0
    res = p.request(PriorQuery()).result(timeout=5)
    assert not res.ok and res.reason.startswith("disabled; topic: too uncertain")
    p2 = TopicPrior(NoneProvider(), TopicPriorConfig(order=order), clock)
    assert p2.request(PriorQuery()).result(timeout=5).reason == "disabled"  # no estimate
