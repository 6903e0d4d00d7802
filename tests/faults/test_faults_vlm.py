"""A misbehaving VLM server (loopback fixture) and secrets: every answer is a flagged result,
no call hangs past its timeout, and a canary key never appears in any output."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from chat_server import ChatServer
from faults.conftest import exit2

CANARY_ENV = "CanaryKey0ab12cd34ef56gh78"  # a key read from $VLM_FAULT_KEY
CANARY_URL = "canarypw-9f8e7d6c5b4a"  # a key given as base_url userinfo
CANARY_SK = "sk-proj-canary1234567890abcdefXYZ"  # a key passed by mistake as an option


@pytest.fixture(scope="module")
def image(demo_data) -> Path:
    return sorted((demo_data / "images").iterdir())[0]


@pytest.mark.parametrize("behaviour,kw,reason", [
    pytest.param("429", {"retry_after_s": 0.2}, "http_429", marks=pytest.mark.fault("vlm_429"),
                 id="vlm_429"),
    pytest.param("500", {}, "http_500", marks=pytest.mark.fault("vlm_500"), id="vlm_500"),
    pytest.param("garbage", {}, "bad_response", marks=pytest.mark.fault("vlm_garbage"),
                 id="vlm_garbage"),
    pytest.param("huge", {}, "bad_response", marks=pytest.mark.fault("vlm_huge"),
                 id="vlm_huge"),
    pytest.param("drip", {"delay_s": 0.3}, "timeout", marks=pytest.mark.fault("vlm_drip"),
                 id="vlm_drip"),
    pytest.param("reset", {}, "connection_error", marks=pytest.mark.fault("vlm_reset"),
                 id="vlm_reset"),
    pytest.param("silence", {}, "timeout", marks=pytest.mark.fault("vlm_silence"),
                 id="vlm_silence"),
])
def test_misbehaving_server(cli, image, behaviour, kw, reason):
    with ChatServer(behaviour, **kw) as srv:
        t0 = time.monotonic()
        rc, out, errors = cli("priors", "ask", "--image", image, "--base-url", srv.base_url,
                              "--prior-option", "timeout_s=2", "--prior-option",
                              "max_retries=1", "--prior-option", "backoff_s=0",
                              "--prior-option", "api_key_env=VLM_FAULT_NO_KEY", "--json")
        took = time.monotonic() - t0
        n = len(srv.requests)
    res = json.loads(out)
    assert rc == 1 and res["ok"] is False and res["reason"] == reason, res
    # one retry on transient failures (not on a 200 with a bad body); each attempt is bounded
    assert n == (1 if reason == "bad_response" else 2) and took < 2 * 2 + 3
    assert "Traceback" not in cli.text


@pytest.mark.fault("cli_timeout_abc")
def test_timeout_not_a_number(cli, image):
    exit2(cli("priors", "ask", "--image", image, "--base-url", "http://127.0.0.1:9/v1",
              "--prior-option", "timeout_s=abc"), "invalid number")
    exit2(cli("localize", "--map", "nowhere", "--images", ".", "--queries", "q.csv", "--out",
              "r.csv", "--prior", "openai", "--prior-option", "timeout_s=abc"))


def _run(*args, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vlm_vpr_ros.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, **(env or {})})


def _no_canary(proc, *canaries) -> None:
    text = proc.stdout + proc.stderr
    for c in canaries:
        for part in c.splitlines():
            assert part not in text, f"secret leaked: {part!r} in\n{text}"
    assert "Traceback" not in text


@pytest.mark.fault("secret_url_userinfo")
def test_key_in_url_and_env_never_logged(image, tmp_path):
    with ChatServer("500") as srv:
        url = srv.base_url.replace("http://", f"http://user:{CANARY_URL}@")
        proc = _run("-vv", "priors", "ask", "--image", image, "--base-url", url,
                    "--prior-option", "max_retries=2", "--prior-option", "backoff_s=0",
                    "--prior-option", "api_key_env=VLM_FAULT_KEY", "--json",
                    env={"VLM_FAULT_KEY": CANARY_ENV})
        sent = srv.request_headers[-1]
    assert proc.returncode == 1 and json.loads(proc.stdout)["reason"] == "http_500"
    assert "retrying" in proc.stderr and "***" not in proc.stdout
    _no_canary(proc, CANARY_URL, CANARY_ENV)
    assert sent.get("Authorization") == f"Bearer {CANARY_ENV}"  # the header only


@pytest.mark.fault("secret_api_key_env")
def test_key_given_as_env_name(image):
    proc = _run("priors", "ask", "--image", image, "--base-url", "http://127.0.0.1:9/v1",
                "--prior-option", f"api_key_env={CANARY_SK}")
    assert proc.returncode == 2 and "NAME of an environment variable" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    _no_canary(proc, CANARY_SK)


@pytest.mark.fault("secret_key_newline")
def test_key_with_newline(image):
    key = CANARY_ENV + "\nsecondline" + CANARY_ENV[::-1]
    proc = _run("-vv", "priors", "ask", "--image", image, "--base-url",
                "http://127.0.0.1:9/v1", "--prior-option", "api_key_env=VLM_FAULT_KEY",
                env={"VLM_FAULT_KEY": key})
    assert proc.returncode == 2 and "line break" in proc.stderr
    _no_canary(proc, key)
