"""The ``openai`` prior provider against a loopback server per dialect (tests/chat_dialects.py):
OpenAI chat and reasoning models, an Azure deployment, Ollama's and vLLM's OpenAI-compatible
routes; `vlm-vpr priors ask` and the node's provider (built from ROS parameters) get a prior
on the first try, the key never appears in any output, and a refused request field is
explained in one line."""

from __future__ import annotations

import json
import logging

import pytest
from chat_server import ChatServer

from vlm_vpr_ros.cli import main
from vlm_vpr_ros.runtime.params import from_params
from vlm_vpr_ros.priors import PriorQuery, create_prior_provider

KEY = "sk-dialect-canary-0123456789abcdefXYZ"
ENV = "VLM_DIALECT_KEY"
# (dialect, the model name a user writes, whether the server demands the key)
DIALECTS = [
    ("openai", "gpt-4.1-mini", True),
    ("openai_reasoning", "gpt-5.4-mini", True),
    ("azure", "gpt-5-mini", True),  # the deployment name, as Azure users name them
    ("ollama", "qwen3-vl:8b", False),
    ("vllm", "Qwen/Qwen3-VL-8B-Instruct", True),
]


@pytest.fixture(scope="module")
def image(demo_data):
    return sorted((demo_data / "images").glob("*.jpg"))[0]


@pytest.fixture(autouse=True)
def _key(monkeypatch):
    monkeypatch.setenv(ENV, KEY)


def ask(capsys, caplog, *args) -> tuple[int, str, str]:
    """``vlm-vpr priors ask`` in-process: (exit status, stdout, stderr and every log record,
    formatted without redaction: a secret there was logged at all)."""
    caplog.clear()
    with caplog.at_level(logging.DEBUG):
        rc = main(["priors", "ask", *map(str, args)])
    out = capsys.readouterr()
    return rc, out.out, out.err + caplog.text


def _server(dialect, model, demands_key, **kw):
    kw = {"lat": -33.8568, "lon": 151.2153, **kw}
    return ChatServer(dialect=dialect, api_key=KEY if demands_key else None, models=(model,),
                      **kw)


@pytest.mark.parametrize("dialect, model, demands_key", DIALECTS,
                         ids=[d[0] for d in DIALECTS])
def test_priors_ask_and_node_provider_first_try(dialect, model, demands_key, image, tmp_path,
                                                capsys, caplog):
    cache = tmp_path / "cache"
    with _server(dialect, model, demands_key) as srv:
        rc, out, logs = ask(capsys, caplog, "--image", image, "--base-url", srv.base_url,
                            "--model", model, "--prior-option", f"api_key_env={ENV}",
                            "--prior-option", f"cache_dir={cache}", "--json")
        res = json.loads(out)
        assert rc == 0 and res["ok"], out
        assert (res["lat"], res["lon"]) == (-33.8568, 151.2153)
        assert res["extra"]["attempts"] == 1 and not srv.rejected  # the first try
        assert res["extra"]["parse_path"] == "text"
        sent, headers = srv.requests[0], srv.request_headers[0]
        url = srv.base_url if dialect == "azure" else f"{srv.base_url}/chat/completions"
        # the node builds its provider from ROS parameters (prior.*), without a cache
        cfg = from_params({"map_dir": str(tmp_path), "prior_provider": "openai",
                           "prior.base_url": srv.base_url, "prior.model": model,
                           "prior.api_key_env": ENV, "prior.max_retries": 0})
        with create_prior_provider(cfg.prior_provider, cfg.prior) as prov:
            node_res = prov.get(PriorQuery(encoded=image.read_bytes()), timeout_s=10)
        assert node_res.ok and node_res.extra["attempts"] == 1 and not srv.rejected
        assert len(srv.requests) == 2
    reasoning = dialect in ("openai_reasoning", "azure")
    assert ("temperature" in sent) != reasoning
    token = "max_completion_tokens" if reasoning else "max_tokens"
    assert sent[token] == (4000 if reasoning else 600) and len({"max_tokens",
                                                                "max_completion_tokens"}
                                                               & set(sent)) == 1
    if dialect == "azure":  # the key in api-key, never in Authorization
        assert headers.get("api-key") == KEY and "Authorization" not in headers
    else:
        assert headers.get("Authorization") == f"Bearer {KEY}"
    files = [p.read_text() for p in cache.rglob("*.json")]
    assert len(files) == 1 and json.loads(files[0])["endpoint"] == url
    for text in (out, logs, *files):  # the canary: in no output, no log record, no cache file
        assert KEY not in text and KEY[10:30] not in text


def test_azure_query_string_kept_and_deployment_family(image, tmp_path, capsys, caplog):
    """An api-version other than the server's is refused (so it was sent); a deployment with
    a name of its own needs model_family=reasoning; without it the refusal says so in one
    line."""
    with ChatServer(dialect="azure", api_key=KEY, deployment="geo-prior") as srv:
        bad = srv.url_for("127.0.0.1", api_version="2099-01-01")
        rc, out, logs = ask(capsys, caplog, "--image", image, "--base-url", bad, "--model",
                            "geo-prior", "--prior-option", f"api_key_env={ENV}")
        assert rc == 1 and "no prior: http_400" in out
        args = ["--image", image, "--base-url", srv.base_url, "--model", "geo-prior",
                "--prior-option", f"api_key_env={ENV}"]
        rc, out, logs = ask(capsys, caplog, *args)
        assert rc == 1 and "no prior: http_400" in out
        advice = [line for line in (out + logs).splitlines() if "temperature=none" in line]
        assert len(advice) == 1 and "'temperature'" in advice[0], out + logs
        rc, out, _ = ask(capsys, caplog, *args, "--prior-option", "model_family=reasoning")
        assert rc == 0, out
        assert srv.request_headers[-1]["api-key"] == KEY


@pytest.mark.parametrize("option, advice", [
    ("token_param=max_tokens", "token_param=max_completion_tokens"),
    ("temperature=0.2", "temperature=none"),
    ("reasoning_effort=extreme", "reasoning_effort"),
])
def test_refused_field_is_one_line_naming_the_option(image, capsys, caplog, option, advice):
    with ChatServer(dialect="openai_reasoning") as srv:
        rc, out, logs = ask(capsys, caplog, "--image", image, "--base-url", srv.base_url,
                            "--model", "gpt-5.4-mini", "--prior-option", option,
                            "--prior-option", "max_retries=3")
        n = len(srv.rejected)
    assert rc == 1 and "no prior: http_400" in out and n == 1  # a 400 is not retried
    lines = [ln for ln in (out + logs).splitlines() if f"prior option {advice}" in ln]
    assert len(lines) == 1, out + logs
    assert option.split("=")[0] in lines[0] and "{" not in lines[0]  # no body dump


def test_reasoning_effort_and_extra_body_pass_through(tmp_path):
    with ChatServer(dialect="vllm", models=("Qwen/Qwen3-VL-8B-Instruct",)) as srv:
        cfg = from_params({  # a JSON string (ROS string parameter) and a dotted key (YAML)
            "map_dir": str(tmp_path), "prior_provider": "openai",
            "prior.base_url": srv.base_url, "prior.model": "Qwen/Qwen3-VL-8B-Instruct",
            "prior.extra_body": '{"top_k": 20, "repetition_penalty": 1.05}',
            "prior.extra_body.chat_template_kwargs.enable_thinking": False,
            "prior.reasoning_effort": "low", "prior.temperature": 0.7, "prior.max_tokens": 300})
        with create_prior_provider(cfg.prior_provider, cfg.prior) as prov:
            assert prov.get(PriorQuery(image=_rgb()), timeout_s=10).ok
    body = srv.requests[0]
    assert body["top_k"] == 20 and body["repetition_penalty"] == 1.05
    assert body["chat_template_kwargs"] == {"enable_thinking": False}
    assert body["reasoning_effort"] == "low" and body["temperature"] == 0.7
    assert body["max_tokens"] == 300 and "max_completion_tokens" not in body


def _rgb():
    import numpy as np

    img = np.zeros((48, 64, 3), np.uint8)
    img[:, :32] = (200, 40, 10)
    return img


@pytest.mark.parametrize("dialect", ["openai", "ollama", "vllm", "azure"])
def test_structured_output_with_model_uncertainty(dialect):
    model = "gpt-5-mini" if dialect == "azure" else "m"
    with ChatServer(dialect=dialect, lat=35.6586, lon=139.7454, uncertainty_km=12.5) as srv:
        with create_prior_provider("openai", {"base_url": srv.base_url, "model": model,
                                              "structured_output": True,
                                              "model_uncertainty": True,
                                              "api_key_env": "VLM_NO_SUCH_KEY"}) as prov:
            res = prov.get(PriorQuery(image=_rgb()), timeout_s=10)
    assert res.ok and (res.prior.lat, res.prior.lon) == (35.6586, 139.7454)
    assert res.extra["parse_path"] == "structured" and res.extra["parse_method"] == "json_schema"
    assert res.extra["model_uncertainty_km"] == 12.5
    assert res.prior.sigma_km is None  # recorded, not used: the fitted error model decides
    schema = srv.requests[0]["response_format"]["json_schema"]
    props = schema["schema"]["properties"]
    assert schema["strict"] and schema["schema"]["required"] == list(props)
    assert list(props)[-3:] == ["latitude", "longitude", "uncertainty_km"]
    assert list(props)[:2] == ["continent", "country"]  # reasoning fields come first


@pytest.mark.parametrize("dialect, structured", [("openai", False), ("vllm", False),
                                                 ("openai", "ignore")])
def test_structured_output_falls_back_to_text(dialect, structured):
    with ChatServer(dialect=dialect, structured=structured, lat=1.2903, lon=103.852) as srv:
        with create_prior_provider("openai", {"base_url": srv.base_url, "model": "m",
                                              "structured_output": True,
                                              "max_retries": 0}) as prov:
            results = [prov.get(PriorQuery(image=_rgb()), timeout_s=10) for _ in range(3)]
    assert all(r.ok and (r.prior.lat, r.prior.lon) == (1.2903, 103.852) for r in results)
    assert {r.extra["parse_path"] for r in results} == {"text_fallback"}
    if structured is False:  # refused once, then text requests only
        assert len(srv.rejected) == 1 and results[0].extra["attempts"] == 2
        assert not any("response_format" in b for b in srv.requests)
    else:  # the server ignored the schema and wrote prose: the text parser read it
        assert results[0].extra["parse_method"] == "labelled"


def test_structured_answers_are_cached_with_their_path(tmp_path):
    opts = {"model": "m", "structured_output": True, "cache_dir": str(tmp_path)}
    with ChatServer() as srv:
        with create_prior_provider("openai", {"base_url": srv.base_url, **opts}) as prov:
            first = prov.get(PriorQuery(image=_rgb()), timeout_s=10)
            second = prov.get(PriorQuery(image=_rgb()), timeout_s=10)
        with create_prior_provider("openai", {"base_url": srv.base_url, "model": "m",
                                              "cache_dir": str(tmp_path)}) as prov:
            text = prov.get(PriorQuery(image=_rgb()), timeout_s=10)  # another answer format
    assert first.extra["parse_path"] == second.extra["parse_path"] == "structured"
    assert second.extra["cached"] and not text.extra["cached"] and len(srv.requests) == 2


def test_config_errors_are_one_line():
    from vlm_vpr_ros.errors import ConfigError

    bad = [({"model_uncertainty": True}, "structured_output"),
           ({"token_param": "max_tokenz"}, "max_completion_tokens"),
           ({"model_family": "big"}, "reasoning"),
           ({"temperature": "hot"}, "temperature"), ({"temperature": 3}, "[0, 2]"),
           ({"extra_body": "[1, 2]"}, "JSON object"), ({"extra_body": "{nope"}, "JSON object"),
           ({"extra_body": {"messages": []}}, "messages"),
           ({"reasoning_effort": "a b"}, "reasoning_effort"),
           ({"structured_output": "maybe"}, "true or false"),
           ({"auth_header": "cookie"}, "api-key"),
           ({"base_url": "https://x.test/v1", "ca_file": "/nonexistent/ca.pem"}, "ca_file")]
    for opts, needle in bad:
        with pytest.raises(ConfigError, match=needle.replace("[", r"\[")) as err:
            create_prior_provider("openai", {"api_key_env": "VLM_NO_SUCH_KEY", **opts})
        assert "\n" not in str(err.value)


@pytest.mark.timeout(120)
def test_node_gets_a_structured_prior_from_a_reasoning_model(demo_map, demo_data, tmp_path,
                                                             monkeypatch):
    """The real node (own process, rclpy + Fast DDS) against the reasoning dialect with
    structured output: the first request is accepted, /diagnostics reports the prior and how
    it was read, and the key is not in the node's log."""
    from node_harness import domain_id, image_msg, node_and_client

    from vlm_vpr_ros.files.images import load_image

    monkeypatch.setenv(ENV, KEY)  # the node process inherits it
    rgb = load_image(sorted((demo_data / "images").glob("*.jpg"))[0])
    with _server("openai_reasoning", "gpt-5.4-mini", True, lat=39.5591, lon=8.8889) as srv:
        params = {"map_dir": str(demo_map), "prior_provider": "openai",
                  "prior.base_url": srv.base_url, "prior.model": "gpt-5.4-mini",
                  "prior.api_key_env": ENV, "prior.structured_output": True,
                  "prior.max_retries": 0, "min_period_s": 0.5, "diagnostics_period_s": 0.5}
        with node_and_client(params, tmp_path / "node.log", domain_id()) as (node, client):
            stamp = [1_700_000_000_000_000_000]

            def tick():
                stamp[0] += 1
                client.image_pub.publish(image_msg(rgb, stamp[0]))

            diag = client.wait_for(lambda: (d := client.latest_diag()).get("prior_ok") == "true"
                                   and d, 60.0, tick=tick, period_s=0.2)
            log = node.log()
        rejected, first = srv.rejected, srv.requests[0]
    assert diag, log[-3000:]
    assert diag["prior_source"] == "openai:gpt-5.4-mini" and diag["prior_parse"] == "structured"
    assert not rejected and "response_format" in first and "temperature" not in first
    assert KEY not in log and KEY[10:30] not in log


def test_results_written_before_the_prior_parse_column_resume(tmp_path):
    """`localize --resume` keeps the rows of a results file written before `prior_parse`."""
    from vlm_vpr_ros.localization.batch import RESULT_FIELDS, read_done_rows

    old = [k for k in RESULT_FIELDS if k != "prior_parse"]
    path = tmp_path / "res.csv"
    path.write_text(",".join(old) + "\n" + ",".join(
        "a.jpg" if k == "file" else "ok" if k == "flags" else "1" for k in old) + "\n")
    rows = read_done_rows(path)
    assert len(rows) == 1 and rows[0]["prior_parse"] == "" and rows[0]["file"] == "a.jpg"


def test_answer_cut_at_the_token_limit_says_to_raise_it(caplog):
    with ChatServer("length", dialect="openai_reasoning") as srv:
        with create_prior_provider("openai", {"base_url": srv.base_url, "model": "o4-mini",
                                              "max_tokens": 200}) as prov:
            res = prov.get(PriorQuery(image=_rgb()), timeout_s=10)
    assert res.reason == "truncated" and "max_completion_tokens=200" in res.extra["detail"]
    assert "raise the prior option max_tokens" in res.extra["detail"]
    assert sum("max_completion_tokens=200" in r.getMessage() for r in caplog.records
               if r.levelname == "WARNING") == 1


def test_a_model_the_server_does_not_have_is_one_line(caplog):
    """Ollama without the model pulled: HTTP 404 with the server's own advice, once."""
    with ChatServer(dialect="ollama", models=("qwen3-vl:8b",)) as srv:
        with create_prior_provider("openai", {"base_url": srv.base_url, "model": "qwen3-vl:32b",
                                              "max_retries": 2}) as prov:
            results = [prov.get(PriorQuery(image=_rgb()), timeout_s=10) for _ in range(2)]
    assert [r.reason for r in results] == ["http_404", "http_404"] and len(srv.rejected) == 2
    assert 'model "qwen3-vl:32b" not found, try pulling it first' in results[0].extra["detail"]
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert sum("try pulling it first" in w for w in warnings) == 1  # not once per request
