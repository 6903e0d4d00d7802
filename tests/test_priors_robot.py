"""The robot's own estimate as a prior (pure core: vlm_vpr_ros/priors/robot.py), its message
adapters (msg_adapters/robot_prior.py) and the ``sigma_m`` column of recorded priors."""

from __future__ import annotations

import concurrent.futures as cf
import logging
import math

import numpy as np
import pytest

from vlm_vpr_ros.errors import ConfigError, DataError
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.priors.provider import Prior, PriorProvider, PriorQuery, PriorResult
from vlm_vpr_ros.priors.robot import (RobotEstimate, TopicPrior, TopicPriorConfig,
                                      sigma_from_covariance)
from vlm_vpr_ros.priors.simple import NoPrior, RecordedPrior, read_prior_csv


class Clock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class Vlm(PriorProvider):
    name = "vlm"

    def __init__(self, ok: bool = True) -> None:
        self.ok, self.asked = ok, 0

    def _compute(self, query):
        self.asked += 1
        if not self.ok:
            return PriorResult.failure(self.name, "http_500")
        return PriorResult(Prior(48.0, 2.0, self.name), self.name)


def _get(p: PriorProvider) -> PriorResult:
    return p.request(PriorQuery()).result(timeout=5)


def test_sigma_from_covariance_is_the_larger_axis():
    assert sigma_from_covariance(100.0, 0.0, 100.0) == pytest.approx(10.0)
    # an ellipse rotated 30 degrees with axes 20 m and 5 m: the larger axis
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    rot = np.array([[c, -s], [s, c]])
    cov = rot @ np.diag([400.0, 25.0]) @ rot.T
    assert sigma_from_covariance(cov[0, 0], cov[0, 1], cov[1, 1]) == pytest.approx(20.0)
    for bad in ((math.nan, 0, 1), (0.0, 0.0, 0.0), (-4.0, 0.0, 4.0), (1.0, 2.0, 1.0)):
        with pytest.raises(ConfigError):
            sigma_from_covariance(*bad)


def test_sigma_grows_with_age_and_stale_estimates_fall_back():
    clock, vlm = Clock(), Vlm()
    p = TopicPrior(vlm, TopicPriorConfig(growth_m_per_s=2.0, max_age_s=60.0), clock)
    assert _get(p).prior.source == "vlm" and vlm.asked == 1  # nothing yet: the VLM
    assert p.update(RobotEstimate(37.77, -122.42, 30.0, 995.0, "navsat")) == ""
    r = _get(p)
    assert r.prior.source == "topic:navsat" and vlm.asked == 1
    assert r.prior.sigma_km * 1000 == pytest.approx(30.0 + 2.0 * 5.0)
    clock.t = 1050.0
    assert _get(p).prior.sigma_km * 1000 == pytest.approx(30.0 + 2.0 * 55.0)
    clock.t = 1056.0  # 61 s old: stale, the VLM answers
    assert _get(p).prior.source == "vlm" and vlm.asked == 2


def test_provider_first_uses_the_robot_when_the_vlm_fails():
    clock = Clock()
    p = TopicPrior(Vlm(ok=False), TopicPriorConfig(order="provider_first"), clock)
    assert not _get(p).ok
    p.update(RobotEstimate(37.77, -122.42, 50.0, 999.0, "pose"))
    assert _get(p).prior.source == "topic:pose"
    p2 = TopicPrior(Vlm(ok=True), TopicPriorConfig(order="provider_first"), clock)
    p2.update(RobotEstimate(37.77, -122.42, 50.0, 999.0, "pose"))
    assert _get(p2).prior.source == "vlm"


def test_bad_estimates_are_ignored_with_one_warning_each(caplog):
    clock = Clock()
    p = TopicPrior(NoPrior(), TopicPriorConfig(max_age_s=60.0, max_future_s=1.0), clock,
                   label="/gps/fix")
    bad = [RobotEstimate(37.7, -122.4, 10.0, 1010.0, "navsat"),   # 10 s in the future
           RobotEstimate(37.7, -122.4, 10.0, 900.0, "navsat"),    # 100 s old
           RobotEstimate(37.7, -122.4, math.nan, 1000.0, "navsat"),
           RobotEstimate(37.7, -122.4, 0.0, 1000.0, "navsat"),
           RobotEstimate(137.7, -122.4, 10.0, 1000.0, "navsat")]
    with caplog.at_level(logging.WARNING, logger="vlm_vpr_ros.priors.robot"):
        for est in bad + bad:
            assert p.update(est)
    assert not _get(p).ok and p.rejected == 10
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 4  # one per kind: stamp (future / old share it), sigma x2 kinds, pos
    assert all("/gps/fix" in m for m in lines)
    assert any("in the future" in m for m in lines) and any("not a valid" in m for m in lines)


def test_navsat_and_pose_messages_become_estimates():
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import NavSatFix

    from msg_adapters.robot_prior import estimate_from_msg
    from vlm_vpr_ros.runtime.metric_frame import MetricFrame

    fix = NavSatFix(latitude=37.77, longitude=-122.42)
    fix.header.stamp.sec, fix.header.stamp.nanosec = 100, 500_000_000
    fix.status.status = 0
    fix.position_covariance = [900.0, 0, 0, 0, 900.0, 0, 0, 0, 100.0]
    fix.position_covariance_type = 2
    est = estimate_from_msg("navsat", fix, None)
    assert (est.lat, est.lon, est.sigma_m, est.stamp_s) == (37.77, -122.42, 30.0, 100.5)
    fix.position_covariance_type = 0
    with pytest.raises(ConfigError, match="UNKNOWN"):
        estimate_from_msg("navsat", fix, None)
    fix.position_covariance_type, fix.status.status = 2, -1
    with pytest.raises(ConfigError, match="NO_FIX"):
        estimate_from_msg("navsat", fix, None)

    frame = MetricFrame("utm", zone=10)
    x, y, _ = frame.project(37.77, -122.42, 0.0)
    for msg in (PoseWithCovarianceStamped(), Odometry()):
        msg.header.frame_id = "utm"
        msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
        cov = [0.0] * 36
        cov[0] = cov[7] = 400.0
        msg.pose.covariance = cov
        est = estimate_from_msg("pose", msg, frame)
        assert haversine_km(est.lat, est.lon, 37.77, -122.42) * 1000 < 0.01
        assert est.sigma_m == pytest.approx(20.0)
        msg.header.frame_id = "odom"
        with pytest.raises(ConfigError, match="'odom' cannot be converted"):
            estimate_from_msg("pose", msg, frame)
    with pytest.raises(ConfigError, match="fixed zone"):
        MetricFrame("utm").unproject(x, y)


def test_recorded_priors_carry_sigma_m(tmp_path, caplog):
    csv = tmp_path / "p.csv"
    csv.write_text("file,lat,lon,sigma_m\na.jpg,37.7,-122.4,100\nb.jpg,37.8,-122.5,\n"
                   "c.jpg,91,-122.6,5\n")
    with caplog.at_level(logging.WARNING):
        prov = RecordedPrior(str(csv))
    a = _get_key(prov, "a.jpg")
    assert a.prior.sigma_km == pytest.approx(0.1)
    assert _get_key(prov, "b.jpg").prior.sigma_km is None  # blank: the source's error model
    assert not _get_key(prov, "c.jpg").ok  # a bad position: no prior (counted)
    assert "1 row(s)" in caplog.text
    assert read_prior_csv(csv) == {"a.jpg": (37.7, -122.4), "b.jpg": (37.8, -122.5)}
    # a sigma_m that is no sigma (-5, nan: tests/test_issue43_priors.py has every kind)
    for cell in ("-5", "nan"):
        csv.write_text(f"file,lat,lon,sigma_m\nd.jpg,37.9,-122.6,{cell}\n")
        with pytest.raises(DataError, match=f"{csv}:2: field sigma_m"):
            RecordedPrior(str(csv))


def _get_key(p: PriorProvider, key: str) -> PriorResult:
    return p.request(PriorQuery(key=key)).result(timeout=5)


def test_cancelling_a_provider_first_request_cancels_the_provider():
    inner: cf.Future = cf.Future()

    class Pending(PriorProvider):
        name = "pending"

        def request(self, query):
            return inner

    p = TopicPrior(Pending(), TopicPriorConfig(order="provider_first"), Clock())
    fut = p.request(PriorQuery())
    assert fut.cancel() and inner.cancelled()


def _hyp(winner_inliers, rival_inliers, rival_km, pu, prior_km, sigma_km):
    from vlm_vpr_ros.types import Candidate, Hypothesis

    la, lo = 37.77, -122.42
    rla = la + rival_km / 111.2
    pla = la - prior_km / 111.2
    cands = [Candidate("w", la, lo, 0.1, "s", inliers=winner_inliers),
             Candidate("r", rla, lo, 0.2, "s", inliers=rival_inliers)]
    return Hypothesis(la, lo, "w", "s", 200.0, cands, prior=Prior(pla, lo, "topic", sigma_km),
                      p_correct=pu, p_correct_without_prior=pu, inliers=winner_inliers,
                      radius95_m=400.0, verification="verified", flags=("verified",))


def test_a_trusted_prior_weighs_in_only_when_consistent_and_supported():
    from vlm_vpr_ros.localization.verification import prior_trust
    from vlm_vpr_ros.localization.verification.status import StatusPolicy

    pol = StatusPolicy(trust_operator_prior=True)
    # honest: the prior (sigma 100 m) is 100 m from the answer, the look-alike 500 m away
    h = _hyp(119, 96, 0.5, 0.551, 0.1, 0.1)
    assert prior_trust.applies(h, pol)
    prior_trust.weigh_trusted_prior(h)
    assert h.p_correct > 0.99 and "prior_inconsistent" not in h.flags
    # the same look-alike only 120 m from the prior: the prior cannot tell them apart
    h = _hyp(119, 96, 0.02, 0.551, 0.1, 0.1)
    prior_trust.weigh_trusted_prior(h)
    assert h.p_correct < 0.95
    # a liar: 2 km off claiming 100 m. Winner far from it: the prior adds nothing
    h = _hyp(119, 96, 0.5, 0.551, 2.0, 0.1)
    prior_trust.weigh_trusted_prior(h)
    assert h.p_correct == 0.551 and "prior_inconsistent" in h.flags
    # ... or a wrong winner near it that geometry does not support (a far place has more
    # inliers: pu 0.06; or noise-level inliers)
    for inl, rival, pu in ((16, 253, 0.059), (9, 11, 0.409)):
        h = _hyp(inl, rival, 2.0, pu, 0.1, 0.1)
        prior_trust.weigh_trusted_prior(h)
        assert h.p_correct == pu and "prior_inconsistent" in h.flags
    # not applied without trust, or for a prior without its own sigma
    assert not prior_trust.applies(_hyp(119, 96, 0.5, 0.5, 0.1, 0.1), StatusPolicy())
    h = _hyp(119, 96, 0.5, 0.5, 0.1, 0.1)
    h.prior = Prior(h.prior.lat, h.prior.lon, "openai")
    assert not prior_trust.applies(h, pol)
