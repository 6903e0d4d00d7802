"""Request options per model family and endpoint, the reading of refusal bodies in the shapes
OpenAI, vLLM and FastAPI servers send, endpoint URLs (query string, Azure auth), proxies from
the environment, and the redaction rules this work depends on."""

from __future__ import annotations

import json

import pytest

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.priors.request import model_family, rejection, request_options
from vlm_vpr_ros.priors.transport import Endpoint, Proxy
from vlm_vpr_ros.redact import redact, redact_obj


@pytest.mark.parametrize("model, family", [
    ("gpt-4o", "chat"), ("gpt-4.1-mini", "chat"), ("gpt-5", "reasoning"),
    ("gpt-5-mini", "reasoning"), ("gpt-5.4-mini", "reasoning"), ("gpt-5.1", "reasoning"),
    ("gpt-5-chat-latest", "chat"), ("o1", "reasoning"), ("o3-mini", "reasoning"),
    ("o4-mini-2025-04-16", "reasoning"), ("openai/o3", "reasoning"), ("qwen3-vl:8b", "chat"),
    ("gpt-oss:20b", "chat"), ("gemini-2.5-flash", "chat"), ("omni-vision", "chat"),
])
def test_model_family(model, family):
    assert model_family(model) == family


@pytest.mark.parametrize("model, url, token, temperature", [
    ("gpt-4o", "https://api.openai.com/v1/chat/completions", "max_completion_tokens", 0.0),
    ("gpt-5-mini", "https://api.openai.com/v1/chat/completions", "max_completion_tokens", None),
    ("gpt-5-mini", "https://r.openai.azure.com/openai/deployments/gpt-5-mini/chat/completions"
     "?api-version=2024-10-21", "max_completion_tokens", None),
    ("my-dep", "http://10.0.0.5/openai/deployments/my-dep/chat/completions?api-version=x",
     "max_completion_tokens", 0.0),
    ("qwen3-vl:8b", "http://localhost:11434/v1/chat/completions", "max_tokens", 0.0),
    ("o4-mini", "http://localhost:8000/v1/chat/completions", "max_completion_tokens", None),
    ("gpt-4o", "https://proxy.example/?next=api.openai.com", "max_tokens", 0.0),
])
def test_defaults_by_family_and_endpoint(model, url, token, temperature):
    opts = request_options(model, url)
    body = opts.body(model, [])
    assert token in body and len({"max_tokens", "max_completion_tokens"} & set(body)) == 1
    assert body.get("temperature") == temperature and ("temperature" in body) == (
        temperature is not None)
    assert body[token] == (4000 if temperature is None and model != "my-dep" else 600)


def test_overrides_and_extra_body_merge():
    opts = request_options("gpt-5", "https://api.openai.com/v1", token_param="none",
                           temperature=0.4, reasoning_effort="minimal",
                           extra_body={"verbosity": "low", "temperature": 1.0})
    body = opts.body("gpt-5", [{"role": "user", "content": "x"}], {"type": "json_schema"})
    assert "max_tokens" not in body and "max_completion_tokens" not in body
    assert body["temperature"] == 1.0  # extra_body is merged last: it wins
    assert body["reasoning_effort"] == "minimal" and body["verbosity"] == "low"
    assert body["response_format"] == {"type": "json_schema"}
    assert request_options("gpt-5", "", family="chat").temperature == 0.0
    assert request_options("gpt-4o", "", temperature="none").temperature is None
    assert request_options("gpt-4o", "", max_tokens="120").max_tokens == 120


@pytest.mark.parametrize("payload, param", [
    ({"error": {"message": "Unsupported parameter: 'max_tokens' is not supported with this "
                           "model. Use 'max_completion_tokens' instead.",
                "type": "invalid_request_error", "param": "max_tokens",
                "code": "unsupported_parameter"}}, "max_tokens"),
    ({"error": {"message": "Unsupported value: 'temperature' does not support 0 with this "
                           "model. Only the default (1) value is supported.", "param": None}},
     "temperature"),  # no param field: named in the message
    ({"object": "error", "message": "response_format json_schema is not supported",
      "type": "BadRequestError", "param": None, "code": 400}, "response_format"),
    ({"detail": [{"loc": ["body", "top_k"], "msg": "Extra inputs are not permitted"}]},
     "top_k"),
    ({"error": {"message": "Invalid value for 'messages[0].role'", "param": "messages[0].role"}},
     None),  # the client's own field: no option to change
    ({"error": {"message": "model not found"}}, None),
])
def test_rejection_names_the_field(payload, param):
    sent = {"model": "m", "messages": [], "max_tokens": 1, "temperature": 0,
            "response_format": {}, "top_k": 20}
    got = rejection(400, json.dumps(payload).encode(), sent)
    assert (got.param if got else None) == param
    if got is not None:
        opts = request_options("m", "", extra_body={"top_k": 20})
        line = got.advice("http://h/v1/chat/completions", opts)
        assert "\n" not in line and "change the prior option" in line
    assert rejection(500, json.dumps(payload).encode(), sent) is None


def test_rejection_message_is_redacted_and_short():
    payload = {"error": {"message": "Unsupported parameter: 'temperature' (request had "
                                    "Authorization: Bearer sk-abcdefghijklmnop1234) " + "x" * 500,
                         "param": "temperature"}}
    got = rejection(400, json.dumps(payload).encode(), {"temperature": 0})
    assert got and "sk-abcdefghijklmnop1234" not in got.message and len(got.message) <= 200


def test_endpoint_urls():
    e = Endpoint.parse("https://res.openai.azure.com/openai/deployments/geo/chat/completions"
                       "?api-version=2025-04-01-preview")
    assert e.target == "/openai/deployments/geo/chat/completions?api-version=2025-04-01-preview"
    assert e.auth_header == "api-key" and e.auth("k") == {"api-key": "k"}
    e = Endpoint.parse("http://localhost:11434/v1/")
    assert e.target == "/v1/chat/completions" and e.auth("k") == {"Authorization": "Bearer k"}
    e = Endpoint.parse("http://u:pw-in-url-123@h:8000/v1?key=AIzaSecretQueryValue0123456789",
                       auth_header="none")
    assert e.auth("k") == {} and "pw-in-url-123" not in e.display
    assert "AIzaSecretQueryValue0123456789" not in e.display and e.display.startswith("http://h")
    for bad in ("ftp://x", "http://", "http://h:99999/v1"):
        with pytest.raises(ConfigError, match="base_url"):
            Endpoint.parse(bad)


def test_proxy_from_the_environment(monkeypatch):
    e = Endpoint.parse("https://api.openai.com/v1")
    monkeypatch.setenv("https_proxy", "http://user%40corp:p%3Ass-proxy-77@proxy.corp:8080")
    monkeypatch.delenv("no_proxy", raising=False)
    monkeypatch.delenv("NO_PROXY", raising=False)
    p = Proxy.for_endpoint(e)
    assert (p.host, p.port) == ("proxy.corp", 8080) and p.display == "http://proxy.corp:8080"
    import base64

    assert base64.b64decode(p.authorization.split()[1]) == b"user@corp:p:ss-proxy-77"
    assert "p:ss-proxy-77" not in redact("password p:ss-proxy-77") and \
        p.authorization.split()[1] not in redact(p.authorization.split()[1])
    assert Proxy.for_endpoint(Endpoint.parse("http://127.0.0.1:9/v1")) is None  # loopback
    monkeypatch.setenv("no_proxy", "api.openai.com")
    assert Proxy.for_endpoint(e) is None
    monkeypatch.delenv("no_proxy")
    monkeypatch.setenv("https_proxy", "https://proxy.corp:443")
    with pytest.raises(ConfigError, match="only http:// proxies"):
        Proxy.for_endpoint(e)


def test_redaction_rules_for_prose_and_counts():
    assert redact("no API key in $OPENAI_API_KEY: sending requests") == \
        "no API key in $OPENAI_API_KEY: sending requests"
    assert redact("set ${OPENAI_API_KEY}: done") == "set ${OPENAI_API_KEY}: done"
    assert redact("max_tokens=600, max_completion_tokens: 4000") == \
        "max_tokens=600, max_completion_tokens: 4000"
    assert redact("OPENAI_API_KEY=sk9x8y7z access_token: abc {api_key: q}") == \
        "OPENAI_API_KEY=*** access_token: *** {api_key: ***}"
    assert redact("api-key: 0123abcd") == "api-key: ***"
    # a name is secret when it ends in a secret word: advice naming an option stays readable
    assert redact("change the prior option token_param=max_completion_tokens") == \
        "change the prior option token_param=max_completion_tokens"
    assert redact("secret_garden: 51.5, tokens: 12") == "secret_garden: 51.5, tokens: 12"
    assert redact("client_secret=a1 SECRET_KEY: b2 proxy_password=c3 auth_token: d4") == \
        "client_secret=*** SECRET_KEY: *** proxy_password=*** auth_token: ***"
    out = redact_obj({"raw": "Authorization: Bearer sk-zzzzzzzzzzzz", "n": [1, "token=abc"]})
    assert out == {"raw": "Authorization: ***", "n": [1, "token=***"]}
