"""msg_adapters.navsat / diagnostics: the NavSatFix and DiagnosticArray the node publishes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msg_adapters.diagnostics import diagnostic_array, format_value, level_name, status_values
from msg_adapters.navsat import (K68, K95, MAX_SIGMA_M, STATUS_FIX, STATUS_NO_FIX, FixPolicy,
                                 fix_fields, horizontal_sigma, navsat_fix)
from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.localization.verification.status import StatusPolicy, stamp_status
from vlm_vpr_ros.priors.provider import Prior, PriorResult
from vlm_vpr_ros.types import Hypothesis


def hyp(sigma=120.0, flags=(), prior=True, r95=float("nan"), p=0.995, p_without=None,
        sigma_km=None, pl=30.0) -> Hypothesis:
    pr_ = Prior(48.85, 2.35, "fixed", sigma_km) if prior else None
    pr = PriorResult(pr_, "fixed") if prior else PriorResult.failure("openai:x", "timeout")
    return Hypothesis(lat=48.8584, lon=2.2945, ref_id="a.jpg", submap="k003",
                      uncertainty_m=sigma, prior=pr_, prior_result=pr, flags=tuple(flags),
                      radius95_m=r95, p_correct=p,
                      p_correct_without_prior=p if p_without is None else p_without,
                      verification="verified" if math.isfinite(p) else "",
                      protection_m=pl if math.isfinite(p) else math.nan)


def test_good_fix_is_status_fix_with_enu_covariance():
    f = fix_fields(hyp(sigma=60.0, r95=90.0))
    sigma = max(60.0 / K68, 90.0 / K95)  # Rayleigh: 68 % and 95 % radii of a 2-D Gaussian
    assert K68 == pytest.approx(1.5096, abs=1e-4) and K95 == pytest.approx(2.4477, abs=1e-4)
    assert f.status == STATUS_FIX and not f.flagged and f.sigma_m == pytest.approx(sigma)
    assert (f.latitude, f.longitude) == (48.8584, 2.2945)
    cov = np.array(f.covariance).reshape(3, 3)
    assert cov[0, 0] == cov[1, 1] == pytest.approx(sigma ** 2)
    assert cov[2, 2] == pytest.approx(1000.0 ** 2)  # default altitude sigma
    assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0
    assert f.altitude == 0.0 and math.isfinite(f.altitude)  # NaN would be dropped downstream
    # a heavy 95 % tail widens sigma beyond the 68 % radius alone
    assert fix_fields(hyp(sigma=60.0, r95=5000.0)).sigma_m == pytest.approx(5000.0 / K95)


def policy(**status) -> FixPolicy:
    return FixPolicy(status=StatusPolicy(**status))


def test_status_rule_needs_verified_p_correct_and_small_sigma():
    # a verified no-prior match is a fix with its real sigma (flags do not matter)
    f = fix_fields(hyp(sigma=30.0, r95=40.0, flags=("no_prior", "global"), prior=False))
    assert f.flagged and f.status == STATUS_FIX and f.sigma_m < 50.0 and f.reason == ""
    # an unverified answer is never a fix, however small its radius (the lens-cap frame on a
    # map without calibration, issue 18); nor one below fix_min_p_correct
    for h, why in ((hyp(sigma=25.0, p=math.nan), "unverified"),
                   (hyp(sigma=25.0, p=0.9), "p_correct 0.900 < 0.99"),
                   (hyp(sigma=25.0, pl=60.0), "protection 60 m >= alert limit 50 m")):
        g = fix_fields(h)
        assert g.status == STATUS_NO_FIX and not g.precise and g.reason == why
    assert fix_fields(hyp(sigma=25.0, p=0.9), policy(fix_min_p_correct=0.85)).precise
    # a wide radius is not a fix even when verified; the threshold is the policy's
    g = fix_fields(hyp(sigma=3000.0, r95=9000.0))
    assert g.status == STATUS_NO_FIX and g.reason.startswith("sigma 3677 m > 50")
    assert g.sigma_m == pytest.approx(9000.0 / K95)  # honest covariance, no inflation
    assert fix_fields(hyp(sigma=3000.0), policy(fix_max_sigma_m=5000.0)).status == STATUS_FIX
    # fallback_status="fix" publishes the others as FIX with a least sigma, decided once: the
    # answer itself carries the status and the widened radii every other output reports
    wide = hyp(sigma=3000.0, r95=9000.0)
    stamp_status(wide, StatusPolicy(fallback_status="fix", fallback_min_sigma_m=1e5))
    assert wide.status == "fix" and wide.status_reason == "fallback: sigma 3677 m > 50 m"
    assert horizontal_sigma(wide) == pytest.approx(1e5)
    h = fix_fields(wide, FixPolicy(altitude_m=35.0, altitude_sigma_m=10.0))
    assert h.status == STATUS_FIX and h.sigma_m == pytest.approx(1e5) and not h.precise
    assert h.altitude == 35.0 and h.covariance[8] == 100.0 and h.reason.startswith("fallback")
    # an unstamped answer gets the same decision from the policy
    g = fix_fields(hyp(sigma=3000.0, r95=9000.0), policy(fallback_status="fix"))
    assert g.status == STATUS_FIX and g.sigma_m == pytest.approx(9000.0 / K95)
    # no match: never a fix, position NaN
    nm = Hypothesis(lat=math.nan, lon=math.nan, ref_id="", submap="", uncertainty_m=2e7,
                    flags=("no_prior", "no_match"), radius95_m=2e7)
    for pol in (FixPolicy(), policy(fallback_status="fix")):
        x = fix_fields(nm, pol)
        assert x.status == STATUS_NO_FIX and all(math.isfinite(v) for v in x.covariance)


def test_prior_resolved_answers_are_fixes_only_with_a_trusted_prior():
    """Decisive only because the prior removed far look-alikes (p_correct without the prior
    below the threshold): NO_FIX unless the prior is trusted."""
    vlm = hyp(sigma=20.0, p=0.99, p_without=0.4)
    operator = hyp(sigma=20.0, p=0.99, p_without=0.4, sigma_km=2.0)
    assert fix_fields(vlm).status == STATUS_NO_FIX
    assert fix_fields(vlm).reason.startswith("prior_resolved")
    assert fix_fields(vlm, policy(trust_prior_for_fix=True)).status == STATUS_FIX
    assert fix_fields(vlm, policy(trust_operator_prior=True)).status == STATUS_NO_FIX
    assert fix_fields(operator, policy(trust_operator_prior=True)).status == STATUS_FIX
    # decisive without the prior as well: a fix whatever the trust
    assert fix_fields(hyp(sigma=20.0, p=0.995, p_without=0.992)).status == STATUS_FIX


def test_the_pipelines_stamped_status_is_published():
    """An answer stamped by the pipeline (under the policy its query ran with) goes out with
    that status and reason, whatever the adapter's policy: NavSatFix, CSV, relocalize answer
    and diagnostics cannot disagree, even when a threshold changes during the query."""
    h = hyp(sigma=20.0, p=0.99, p_without=0.99)
    h.status, h.status_reason = "no_fix", "p_correct 0.990 < 0.995"
    f = fix_fields(h)
    assert f.status == STATUS_NO_FIX and f.reason == "p_correct 0.990 < 0.995"
    h = hyp(sigma=20.0, p=0.9)
    h.status = "fix"
    assert fix_fields(h).status == STATUS_FIX and fix_fields(h).precise


@pytest.mark.parametrize("bad", [math.inf, math.nan, -5.0, 0.0, 1e12])
def test_covariance_always_finite(bad):
    f = fix_fields(hyp(sigma=bad))
    assert all(math.isfinite(v) for v in f.covariance)
    assert 0 < f.sigma_m <= MAX_SIGMA_M


def test_navsatfix_message():
    from sensor_msgs.msg import NavSatFix, NavSatStatus

    msg = navsat_fix(hyp(sigma=50.0 * K68), 1_700_000_000_123_456_789, "camera_link")
    assert isinstance(msg, NavSatFix)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert msg.header.frame_id == "camera_link"
    assert msg.status.status == NavSatStatus.STATUS_FIX and msg.status.service == 0
    assert msg.position_covariance_type == NavSatFix.COVARIANCE_TYPE_APPROXIMATED
    assert list(msg.position_covariance)[:5] == [2500.0, 0.0, 0.0, 0.0, 2500.0]
    flagged = navsat_fix(hyp(sigma=5000.0, flags=("no_prior",), prior=False, p=0.5), 0, "c")
    assert flagged.status.status == NavSatStatus.STATUS_NO_FIX
    assert flagged.latitude == pytest.approx(48.8584)  # the guess is still visible


def test_diagnostic_array():
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    arr = diagnostic_array(2_500_000_000, "vlm_vpr_node: VPR", "vlm_vpr", "WARN", "flagged",
                           {"frames_received": 12, "prior_ok": False, "sigma_m": 1234.5678,
                            "last_error": None})
    assert isinstance(arr, DiagnosticArray)
    assert (arr.header.stamp.sec, arr.header.stamp.nanosec) == (2, 500_000_000)
    st = arr.status[0]
    assert st.level == DiagnosticStatus.WARN and level_name(st.level) == "WARN"
    assert (st.name, st.hardware_id, st.message) == ("vlm_vpr_node: VPR", "vlm_vpr", "flagged")
    assert status_values(arr) == {"frames_received": "12", "prior_ok": "false",
                                  "sigma_m": "1234.5678", "last_error": ""}
    assert status_values(arr, "other") == {}
    with pytest.raises(ConfigError, match="choices: OK, WARN, ERROR, STALE"):
        diagnostic_array(0, "n", "h", "BAD", "", {})
    assert level_name(2) == "ERROR" and format_value(math.nan) == "nan"


def test_diagnostics_keep_coordinates_in_full_precision():
    """A fix's lat/lon in /diagnostics read back as the same floats (not 6 significant
    digits: -122.445 for -122.44512345678901 is 1 km off)."""
    lat, lon = 37.77491234567891, -122.44512345678901
    arr = diagnostic_array(0, "n", "h", "OK", "", {"last_lat": lat, "last_lon": lon,
                                                     "query_ms": 12.35})
    values = status_values(arr)
    assert float(values["last_lat"]) == lat and float(values["last_lon"]) == lon
    assert values["last_lon"] == "-122.445123456789" and values["query_ms"] == "12.35"


def test_candidates_array_puts_the_answer_first():
    from diagnostic_msgs.msg import DiagnosticStatus

    from msg_adapters.debug import candidates_array

    rows = [{"rank": "1", "ref_id": "a.jpg", "inliers": "274"},
            {"rank": "2", "ref_id": "b.jpg", "inliers": ""}]
    plain = candidates_array(3_000_000_001, "n: candidate", "hw", rows)
    assert [s.name for s in plain.status] == ["n: candidate 1", "n: candidate 2"]
    assert (plain.header.stamp.sec, plain.header.stamp.nanosec) == (3, 1)
    answer = {"status": "STATUS_NO_FIX", "status_reason": "p_correct 0.412 < 0.95",
              "p_correct": "0.4120"}
    arr = candidates_array(0, "n: candidate", "hw", rows, ("n: answer", False, answer))
    first = arr.status[0]
    assert (first.name, first.level, first.hardware_id) == ("n: answer", DiagnosticStatus.WARN,
                                                            "hw")
    assert first.message == "STATUS_NO_FIX: p_correct 0.412 < 0.95"
    assert {kv.key: kv.value for kv in first.values} == answer
    assert [s.message for s in arr.status[1:]] == ["a.jpg", "b.jpg"]
    fix = candidates_array(0, "n", "hw", [], ("n: answer", True, {"status": "STATUS_FIX"}))
    assert fix.status[0].level == DiagnosticStatus.OK and fix.status[0].message == "STATUS_FIX"
