"""Prior providers none / fixed / recorded and the provider registry."""

import concurrent.futures as cf

import pytest

from vlm_vpr_ros.errors import ConfigError, DataError, PriorError
from vlm_vpr_ros.priors import PriorQuery, create_prior_provider
from vlm_vpr_ros.priors.provider import PriorProvider, PriorResult


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


def test_recorded_names_in_two_folders_are_ambiguous_and_zero_zero_is_no_prior(tmp_path):
    """Two recorded rows share a file name in different folders: a query known only by that
    name gets no prior (before: the last row, silently); the exact key still finds its row.
    (0, 0) is a placeholder row, as the VLM's null-island answers are flagged."""
    csv = tmp_path / "p.csv"
    csv.write_text("file,lat,lon\nday/a.jpg,10.5,-20.25\nnight/a.jpg,-33.9,151.2\n"
                   "z.jpg,0,0\n")
    p = create_prior_provider("recorded", {"path": str(csv)})
    assert p.get(PriorQuery(key="a.jpg")).reason == "ambiguous_key"
    assert p.get(PriorQuery(key="elsewhere/a.jpg")).reason == "ambiguous_key"
    assert p.get(PriorQuery(key="night/a.jpg")).prior.lat == -33.9
    assert p.get(PriorQuery(key="z.jpg")).reason == "not_recorded"
    answers = tmp_path / "answers.csv"
    answers.write_text('filename,response\nday/a.jpg,"latitude 10.5, longitude -20.25"\n'
                       'night/a.jpg,"latitude -33.9, longitude 151.2"\n')
    a = create_prior_provider("answers", {"path": str(answers)})
    assert a.get(PriorQuery(key="a.jpg")).reason == "ambiguous_key"
    assert a.get(PriorQuery(key="day/a.jpg")).prior.lat == 10.5


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
