"""The ``answers`` provider (recorded raw VLM answers) and the ``vlm-vpr priors`` CLI."""

from __future__ import annotations

import csv
import json

import pytest
from chat_server import ChatServer

from vlm_vpr_ros.cli import main
from vlm_vpr_ros.errors import DataError
from vlm_vpr_ros.priors import PriorQuery, create_prior_provider

ANSWERS = [
    ("a.jpg", '```json\n{"latitude": "10.0", "longitude": "20.0"}\n```'),  # exact
    ("b.jpg", "Latitude: 10.09, Longitude: 20.0"),  # ~10 km north (robust only)
    ("c.jpg", '{"latitude": 14.5, "longitude": 20.0}'),  # ~500 km north
    ("d.jpg", "I'm sorry, I can't help with that."),  # refusal = miss
    ("e.jpg", '{"latitude": 1, "longitude": 2}'),  # no ground truth: not scored
]
TRUTH = [("a.jpg", 10.0, 20.0), ("b.jpg", 10.0, 20.0), ("c.jpg", 10.0, 20.0),
         ("d.jpg", 10.0, 20.0), ("z.jpg", 0.0, 0.0)]


def _write(path, header, rows):
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return path


@pytest.fixture()
def answers_csv(tmp_path):
    return _write(tmp_path / "my-vlm.csv", ["filename", "system-prompt", "response"],
                  [(f, "prompt", r) for f, r in ANSWERS])


@pytest.fixture(params=["im2gps", "plain"])
def truth_csv(tmp_path, request):
    if request.param == "im2gps":
        return _write(tmp_path / "gt.csv", ["IMG_ID", "AUTHOR", "LAT", "LON"],
                      [(f, "x", la, lo) for f, la, lo in TRUTH])
    return _write(tmp_path / "gt.csv", ["file", "lat", "lon"], TRUTH)


def test_answers_provider_looks_up_by_key_and_basename(answers_csv):
    prov = create_prior_provider("answers", {"path": str(answers_csv)})
    res = prov.get(PriorQuery(key="a.jpg"))
    assert res.ok and (res.prior.lat, res.prior.lon) == (10.0, 20.0)
    assert res.source == "answers:my-vlm" and res.extra["parse_method"] == "fenced_json"
    assert prov.get(PriorQuery(key="some/dir/b.jpg")).ok
    assert prov.get(PriorQuery(key="d.jpg")).reason == "refusal"
    assert prov.get(PriorQuery(key="nope.jpg")).reason == "not_recorded"
    assert prov.get(PriorQuery()).reason == "no_key"
    strict = create_prior_provider("answers", {"path": str(answers_csv), "parser": "strict"})
    assert strict.get(PriorQuery(key="b.jpg")).reason == "no_coordinates"


def test_answers_provider_bad_inputs(tmp_path):
    with pytest.raises(DataError, match="filename,response"):
        create_prior_provider("answers", {"path": str(_write(tmp_path / "x.csv", ["a"], []))})
    with pytest.raises(DataError, match="not found"):
        create_prior_provider("answers", {"path": str(tmp_path / "missing.csv")})


def test_score_json(answers_csv, truth_csv, capsys):
    rc = main(["priors", "score", "--answers", str(answers_csv), "--ground-truth",
               str(truth_csv), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and set(out) == {"images", "readable", "accuracy", "median_km"}
    assert out["images"] == 4 and out["readable"] == 3
    # errors: 0 km, ~10.0 km, ~500 km, miss -> hits out of 4 at each threshold
    assert out["accuracy"] == {"1km": 25.0, "25km": 50.0, "200km": 50.0, "750km": 75.0,
                               "2500km": 75.0}
    # median of (0, 10, 500, miss=worst) is the mean of the middle two: (10 + 500) / 2
    assert 250 < out["median_km"] < 260


def test_score_table_all_parsers_and_details(answers_csv, truth_csv, tmp_path, capsys):
    details = tmp_path / "details.csv"
    assert main(["priors", "score", "--answers", str(answers_csv), "--ground-truth",
                 str(truth_csv), "--parser", "all", "--details", str(details)]) == 0
    out = capsys.readouterr().out
    assert "my-vlm [strict]" in out and "2/4" in out  # b.jpg is prose: strict misses it
    assert "my-vlm [robust]" in out and "3/4" in out
    rows = list(csv.DictReader(details.open()))
    assert len(rows) == 12 and {r["parser"] for r in rows} == {"strict", "robust", "paper"}


def test_score_json_refuses_several_tables(answers_csv, truth_csv, capsys):
    assert main(["priors", "score", "--answers", str(answers_csv), "--ground-truth",
                 str(truth_csv), "--parser", "all", "--json"]) == 2
    assert capsys.readouterr().out == ""


def test_ask_against_the_fixture_server(demo_data, capsys):
    image = sorted((demo_data / "images").glob("*.jpg"))[0]
    with ChatServer(lat=35.0, lon=139.0) as srv:
        rc = main(["priors", "ask", "--image", str(image), "--base-url", srv.base_url,
                   "--model", "fixture-vlm", "--json"])
        out = json.loads(capsys.readouterr().out)
        assert rc == 0 and out["ok"] and (out["lat"], out["lon"]) == (35.0, 139.0)
        assert out["source"] == "openai:fixture-vlm"
        srv.set(behaviour="refusal")
        assert main(["priors", "ask", "--image", str(image), "--base-url", srv.base_url]) == 1
        assert "no prior: refusal" in capsys.readouterr().out
    assert main(["priors", "ask", "--image", str(demo_data / "nope.jpg")]) == 2
