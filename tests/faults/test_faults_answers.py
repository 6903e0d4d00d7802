"""Round 4 (issue 28), VLM endpoints and secrets: answers that are not final or name two
places are never a prior; answers that are not an OpenAI API say so in one line; every
secret-named URL parameter and every echo of a configured key is masked."""

from __future__ import annotations

import base64
import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

KEY = "Qm7xT2vK9pL4wR8nZ3cY6hB1dF5gJ0sE"  # the configured key (env), a canary
SUB = "subkey-6e1f9a2b7c3d4e5f8091a2b3"  # a key in the base URL's query string


class RawServer:
    """Answers each request with ``reply(n, request_bytes) -> bytes`` written raw on the
    socket, then closes it (full control over status line, headers and body)."""

    def __init__(self, reply) -> None:
        self.reply, self.requests = reply, []
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self._t = threading.Thread(target=self._serve, daemon=True)
        self._t.start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            with conn:
                data = b""
                while b"\r\n\r\n" not in data:
                    chunk = conn.recv(65536)
                    if not chunk:
                        break
                    data += chunk
                head, _, body = data.partition(b"\r\n\r\n")
                n = next((int(line.split(b":")[1]) for line in head.split(b"\r\n")
                          if line.lower().startswith(b"content-length:")), 0)
                while len(body) < n:
                    chunk = conn.recv(65536)
                    if not chunk:
                        break
                    body += chunk
                self.requests.append(head + b"\r\n\r\n" + body)
                try:
                    conn.sendall(self.reply(len(self.requests), head))
                except OSError:
                    pass

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/v1"

    def close(self) -> None:
        self.sock.close()


def http(status: str, body: bytes, ctype: str = "application/json", extra: str = "",
         length: int | None = None) -> bytes:
    n = len(body) if length is None else length
    return (f"HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {n}\r\n{extra}"
            "Connection: close\r\n\r\n").encode() + body


def completion(content, finish: str = "stop", **message) -> bytes:
    return json.dumps({"choices": [{"index": 0, "finish_reason": finish, "message": {
        "role": "assistant", "content": content, **message}}]}).encode()


@pytest.fixture(scope="module")
def image(demo_data) -> Path:
    return sorted((demo_data / "images").iterdir())[0]


def ask(image, url, *opts, env=None) -> tuple[subprocess.CompletedProcess, dict]:
    proc = subprocess.run(
        [sys.executable, "-m", "vlm_vpr_ros.cli", "-vv", "priors", "ask", "--image",
         str(image), "--base-url", url, "--json", "--prior-option", "max_retries=1",
         "--prior-option", "backoff_s=0", "--prior-option", "timeout_s=5",
         "--prior-option", "structured_output=false", "--prior-option",
         "api_key_env=VLM_FAULT_KEY", *opts],
        capture_output=True, text=True, timeout=120,
        env={**os.environ, "VLM_FAULT_KEY": KEY, **(env or {})})
    assert "Traceback" not in proc.stderr, proc.stderr
    return proc, json.loads(proc.stdout)


def serve(reply):
    srv = RawServer(reply if callable(reply) else (lambda n, h: reply))
    return srv


PARIS = "Could it be Paris (latitude 48.8566, longitude 2.3522)? No — the signs are"


@pytest.mark.fault("answer_cut_or_ambiguous")
def test_cut_or_two_place_answers_are_not_priors(image):
    """An answer cut at the token limit whose only coordinates are a guess the model was
    still weighing, and an answer offering two places: flagged, never a prior."""
    srv = serve(http("200 OK", completion(PARIS, "length")))
    try:
        proc, res = ask(image, srv.url)
    finally:
        srv.close()
    assert res["ok"] is False and res["reason"] == "truncated", res
    assert res["lat"] is None and res["extra"]["answer_lat"] == pytest.approx(48.8566)
    assert "cut at" in proc.stderr and "max_tokens" in proc.stderr
    two = ('It is either Paris {"latitude": 48.8566, "longitude": 2.3522} or San Francisco '
           '{"latitude": 37.7749, "longitude": -122.4194}.')
    srv = serve(http("200 OK", completion(two)))
    try:
        _, res = ask(image, srv.url)
    finally:
        srv.close()
    assert res["ok"] is False and res["reason"] == "suspicious_ambiguous", res
    one = ('The Eiffel Tower: 48.8584° N, 2.2945° E. {"latitude": 48.8584, '
           '"longitude": 2.2945}')  # the same place twice is one answer
    srv = serve(http("200 OK", completion(one)))
    try:
        _, res = ask(image, srv.url)
    finally:
        srv.close()
    assert res["ok"] is True and res["lat"] == pytest.approx(48.8584)


@pytest.mark.fault("vlm_not_an_api")
def test_answers_that_are_not_an_openai_api_say_so(image):
    """A 200 text/html login page, `content: null` with the answer only in `reasoning`,
    more than 100 response headers: one line saying what the endpoint did."""
    page = b"<html><body><form>Sign in to continue</form></body></html>"
    srv = serve(http("200 OK", page, "text/html; charset=utf-8"))
    try:
        proc, res = ask(image, srv.url)
    finally:
        srv.close()
    assert res["reason"] == "bad_response" and len(srv.requests) == 1
    assert ("did not answer as an OpenAI API (content-type text/html"
            in res["extra"]["detail"]) and "content-type text/html" in proc.stderr
    srv = serve(http("200 OK", completion(None, reasoning='{"latitude": 48.8, '
                                                            '"longitude": 2.3}')))
    try:
        proc, res = ask(image, srv.url)
    finally:
        srv.close()
    assert res["ok"] is False and res["reason"] == "reasoning_only", res
    assert "only the model's reasoning" in res["extra"]["detail"]
    headers = "".join(f"X-Filler-{i}: {i}\r\n" for i in range(150))
    srv = serve(http("200 OK", completion('{"latitude": 48.8, "longitude": 2.3}'),
                     extra=headers))
    try:
        proc, res = ask(image, srv.url)
    finally:
        srv.close()
    assert res["reason"] == "bad_response" and res["reason"] != "connection_error"
    assert "header" in res["extra"]["detail"] and "OpenAI API" in res["extra"]["detail"]


@pytest.mark.fault("vlm_body_cut")
def test_body_cut_off_is_retried(image):
    """A body shorter than its Content-Length (the connection closed mid-answer) is a
    transport failure: retried, and the retry's answer is used."""
    good = completion('{"latitude": 48.8584, "longitude": 2.2945}')

    def reply(n, head):
        if n == 1:
            return http("200 OK", good[:len(good) // 2], length=len(good))
        return http("200 OK", good)

    srv = serve(reply)
    try:
        proc, res = ask(image, srv.url)
    finally:
        srv.close()
    assert len(srv.requests) == 2 and res["ok"] is True, (res, proc.stderr)
    assert res["lat"] == pytest.approx(48.8584) and "cut off" in proc.stderr
    srv = serve(http("200 OK", good[:len(good) // 2], length=len(good)))
    try:
        _, res = ask(image, srv.url)
    finally:
        srv.close()
    assert len(srv.requests) == 2 and res["reason"] == "connection_error"


@pytest.mark.fault("secret_query_and_encodings")
def test_secret_query_parameters_and_echo_encodings(image, tmp_path):
    """`?subscription-key=` in the base URL (-vv, retries, the answer cache) and a 400 body
    echoing the configured key base64-encoded, upper-cased and split in two: never shown."""
    cache = tmp_path / "cache"
    b64 = base64.b64encode(f"Bearer {KEY}".encode()).decode()
    echo = json.dumps({"error": {"message": f"bad key {b64} / {KEY.upper()} / "
                                            f"{KEY[:15]} {KEY[15:]} / {SUB.upper()}",
                                 "param": None}}).encode()
    answer = completion(f'{{"latitude": 48.8584, "longitude": 2.2945}} url={SUB}')

    def reply(n, head):
        return (http("500 Internal Server Error", b"{}") if n == 1 else
                http("400 Bad Request", echo) if n <= 3 else http("200 OK", answer))

    srv = serve(reply)
    try:
        runs = []
        for _ in range(3):  # 500 + 400 (retried, then refused), 400, then a cached answer
            url = f"{srv.url}?subscription-key={SUB}&api-version=2024-10-21"
            runs.append(ask(image, url, "--prior-option", f"cache_dir={cache}"))
    finally:
        srv.close()
    assert f"subscription-key={SUB}".encode() in srv.requests[0]  # the server did get it
    assert runs[-1][1]["ok"] is True
    seen = "".join(p.stdout + p.stderr for p, _ in runs)
    seen += "".join(f.read_text() for f in cache.rglob("*") if f.is_file())
    assert "subscription-key=***" in seen and "HTTP 400" in seen
    for secret in (SUB, KEY, KEY.upper(), b64[8:-8], KEY[:15], KEY[15:], SUB.upper()):
        assert secret not in seen, f"secret leaked: {secret!r}"


def test_redaction_encodings_unit():
    """The redaction rules themselves, against independently built encodings."""
    import urllib.parse

    from vlm_vpr_ros.redact import redact, register_secret, secret_query_name

    key = "ZyXw-9876-abcdEFGH-ijkl-5432"
    register_secret(key)
    for echo in (key, key.lower(), key.upper(), urllib.parse.quote(key, safe=""),
                 key.encode().hex(), base64.b64encode(key.encode()).decode(),
                 base64.urlsafe_b64encode(b"user:" + key.encode()).decode(),
                 base64.b64encode(b"xy" + key.encode() + b"tail").decode()):
        out = redact(f"echo [{echo}] end")
        assert "***" in out and out.startswith("echo [") and out.endswith("] end"), out
        for piece in (key[:10], key[-10:]):
            assert piece.lower() not in out.lower()
    assert "***" in redact(f"{key[:13]}\n{key[13:]}").split("\n")[1]
    for name in ("subscription-key", "api-key", "key", "token", "sig", "code",
                 "access_token", "X-Api-Key", "sv_signature", "client_secret"):
        assert secret_query_name(name), name
        assert redact(f"https://h/x?a=1&{name}=v4lue9&b=2") == f"https://h/x?a=1&{name}=***&b=2"
    for name in ("api-version", "model", "deployment", "max_tokens", "keyboard"):
        assert not secret_query_name(name), name
    assert redact("https://h/x?api-version=2024-10-21") == "https://h/x?api-version=2024-10-21"


# -- round 5 (issue 43) --------------------------------------------------------------------------
@pytest.mark.fault("robot_prior_sigma_grown")
def test_a_robot_estimate_grown_past_every_sigma_is_refused(caplog, demo_map, demo_data):
    """Growth 1,000 m/s and max_age_s 86,400 (both in range), an estimate 30,000 s old: its
    sigma grew to 30,000 km, past the error model's range (before: every relocalization
    failed with 'error model ...'). Now: too uncertain, the provider answers and the query is
    localized with it."""
    import logging

    from vlm_vpr_ros.files.images import load_image
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.priors import create_prior_provider
    from vlm_vpr_ros.priors.provider import PriorQuery
    from vlm_vpr_ros.priors.robot import RobotEstimate, TopicPrior, TopicPriorConfig

    now = [1_000_000.0]
    with caplog.at_level(logging.WARNING, logger="vlm_vpr_ros.priors.robot"):
        cfg = TopicPriorConfig(growth_m_per_s=1000.0, max_age_s=86_400.0)
    assert "too uncertain" in caplog.text
    fixed = create_prior_provider("fixed", {"lat": 48.85, "lon": 2.35})
    topic = TopicPrior(fixed, cfg, clock=lambda: now[0])
    assert topic.update(RobotEstimate(37.77, -122.42, 10.0, now[0] - 1.0, "navsat")) == ""
    now[0] += 29_999.0
    res = topic.request(PriorQuery()).result(timeout=5)
    assert res.ok and res.prior.source == "fixed" and topic.used == 0
    prior, why = topic.current()
    assert prior is None and why.startswith("too uncertain")
    name = sorted(p.name for p in (demo_data / "images").iterdir())[0]
    hyp = LocalizationPipeline.open(demo_map).localize_image(
        load_image(demo_data / "images" / name), res)
    assert hyp.prior is not None and "prior_failed" not in hyp.flags


# -- round 5 (issue 43): found elsewhere ----------------------------------------------------------
@pytest.mark.fault("localizer_prior_sigma_guard")
def test_a_providers_sigma_outside_the_rule_is_an_invalid_prior(pipeline, demo_data):
    """A provider of the user's answers past every entry point's check: before, 1e-300 km was an
    OverflowError row and 30,000 km an 'error model' row on every query. Now the localizer's
    own guard (the one sigma rule) flags it and answers as without a prior."""
    from vlm_vpr_ros.localization.batch import localize_files
    from vlm_vpr_ros.priors import create_prior_provider
    from vlm_vpr_ros.priors.provider import Prior, PriorProvider, PriorResult

    class Mine(PriorProvider):
        name = "mine"

        def __init__(self, sigma_km: float) -> None:
            self.sigma_km = sigma_km

        def _compute(self, query):
            return PriorResult(Prior(39.2, 9.1, "mine", self.sigma_km), "mine")

    files = sorted(p.name for p in (demo_data / "images").iterdir())[:2]
    ref = list(localize_files(pipeline, create_prior_provider("none"), demo_data / "images",
                              files))
    for sigma_km in (1e-300, 3e4):
        rows = list(localize_files(pipeline, Mine(sigma_km), demo_data / "images", files))
        for r, r0 in zip(rows, ref):
            flags = r["flags"].split("|")
            assert {"prior_failed", "prior_invalid", "no_prior"} <= set(flags), r
            assert "error" not in flags and r["ref_id"] == r0["ref_id"] != ""
            assert (r["lat"], r["lon"]) == (r0["lat"], r0["lon"])
