"""Prior providers none / fixed / recorded and the provider registry."""

import concurrent.futures as cf

import pytest

from vlm_vpr_ros.errors import ConfigError, DataError, PriorError
from vlm_vpr_ros.priors import PriorQuery, create_prior_provider
from vlm_vpr_ros.priors.base import PriorProvider, PriorResult


def test_none_gives_no_prior_without_blocking():
    p = create_prior_provider("none")
    fut = p.request(PriorQuery(key="a.jpg"))
    assert isinstance(fut, cf.Future) and fut.done()
    res = fut.result()
    assert res.prior is None and res.reason == "disabled" and not res.ok


def test_fixed_prior_and_validation():
    res = create_prior_provider("fixed", {"lat": 48.85, "lon": 2.35}).get(PriorQuery())
    assert res.ok and (res.prior.lat, res.prior.lon, res.prior.source) == (48.85, 2.35, "fixed")
    with pytest.raises(PriorError, match="not a valid"):
        create_prior_provider("fixed", {"lat": 95.0, "lon": 0.0})


def test_recorded_lookup_by_name_and_basename(tmp_path):
    csv = tmp_path / "p.csv"
    csv.write_text("file,lat,lon\nimgs/a.jpg,10.5,-20.25\nb.jpg,nan,3\nc.jpg,1,x\n"
                   "d.jpg,3_9.5591,1\n")
    p = create_prior_provider("recorded", {"path": str(csv)})
    assert p.get(PriorQuery(key="imgs/a.jpg")).prior.lat == 10.5
    assert p.get(PriorQuery(key="other/dir/a.jpg")).prior.lon == -20.25
    assert p.get(PriorQuery(key="b.jpg")).reason == "not_recorded"  # NaN row = no prior
    assert p.get(PriorQuery(key="d.jpg")).reason == "not_recorded"  # "3_9.5591" is no number
    assert p.get(PriorQuery(key="zzz.jpg")).reason == "not_recorded"
    assert p.get(PriorQuery()).reason == "no_key"


def test_recorded_bad_files(tmp_path):
    with pytest.raises(DataError, match="not found"):
        create_prior_provider("recorded", {"path": str(tmp_path / "missing.csv")})
    bad = tmp_path / "bad.csv"
    bad.write_text("name,latitude\n")
    with pytest.raises(DataError, match="missing column"):
        create_prior_provider("recorded", {"path": str(bad)})


def test_registry_errors_list_choices():
    with pytest.raises(ConfigError, match="choices: .*fixed.*none.*recorded"):
        create_prior_provider("gpt-5-oracle")
    with pytest.raises(ConfigError, match="unknown option"):
        create_prior_provider("fixed", {"lat": 1.0, "lon": 2.0, "alt": 3.0})


def test_a_buggy_provider_becomes_a_failure_value():
    class Broken(PriorProvider):
        name = "broken"

        def _compute(self, query):
            raise RuntimeError("boom")

    res = Broken().get(PriorQuery())
    assert isinstance(res, PriorResult) and res.prior is None and "boom" in res.reason
