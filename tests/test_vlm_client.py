"""The ``openai`` prior provider against a real loopback HTTP server (tests/chat_server.py):
answers, retries with back-off, 429 Retry-After, timeouts, rate limit, cancellation, cache."""

from __future__ import annotations

import base64
import json
import logging
import socket
import threading
import time

import cv2
import numpy as np
import pytest
from chat_server import ChatServer

from vlm_vpr_ros.errors import ConfigError, PriorError
from vlm_vpr_ros.priors import PriorQuery, create_prior_provider

SECRET = "sk-test-DO-NOT-LEAK-1234567890"


@pytest.fixture()
def server():
    with ChatServer() as srv:
        yield srv


def _provider(srv, **kw):
    opts = {"base_url": srv.base_url, "model": "fixture-vlm", "api_key_env": "VLM_TEST_KEY",
            "timeout_s": 5.0, "max_retries": 2, "backoff_s": 0.05, **kw}
    return create_prior_provider("openai", opts)


def _query(color=(200, 30, 10), size=(64, 48)):
    img = np.zeros((size[1], size[0], 3), np.uint8)
    img[:] = color
    return PriorQuery(image=img, key="frame_0001")


@pytest.fixture(autouse=True)
def _key(monkeypatch):
    monkeypatch.setenv("VLM_TEST_KEY", SECRET)


@pytest.mark.parametrize("behaviour, method", [("ok", "json"), ("fenced", "fenced_json"),
                                               ("prose", "labelled")])
def test_answers_are_parsed(server, behaviour, method):
    server.set(behaviour=behaviour, lat=-33.8568, lon=151.2153)
    with _provider(server) as prov:
        res = prov.get(_query(), timeout_s=10)
    assert res.ok, res
    assert (res.prior.lat, res.prior.lon) == (-33.8568, 151.2153)
    assert res.source == res.prior.source == "openai:fixture-vlm"
    assert res.extra["parse_method"] == method and res.extra["attempts"] == 1
    assert res.latency_s > 0 and res.raw_text


def test_request_body_headers_and_image(server):
    with _provider(server, temperature=0.3, max_image_side=40) as prov:
        assert prov.get(_query(color=(200, 30, 10), size=(80, 60)), timeout_s=10).ok
    body = server.requests[0]
    assert body["model"] == "fixture-vlm" and body["temperature"] == 0.3
    assert body["messages"][0]["role"] == "system"
    parts = body["messages"][1]["content"]
    assert "latitude" in parts[0]["text"] and "continent" in parts[0]["text"].lower()
    url = parts[1]["image_url"]["url"]
    assert url.startswith("data:image/jpeg;base64,")
    bgr = cv2.imdecode(np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8),
                       cv2.IMREAD_COLOR)
    assert bgr.shape == (30, 40, 3)  # downscaled to max side 40, aspect kept
    b, g, r = bgr[15, 20].astype(int)
    assert r > 150 and b < 60  # RGB red stays red (no channel swap)
    assert server.request_headers[0]["Authorization"] == f"Bearer {SECRET}"


def test_encoded_bytes_are_sent_unchanged_when_small(server):
    ok, buf = cv2.imencode(".png", np.full((20, 30, 3), 128, np.uint8))
    with _provider(server) as prov:
        assert prov.get(PriorQuery(encoded=buf.tobytes()), timeout_s=10).ok
    url = server.requests[0]["messages"][1]["content"][1]["image_url"]["url"]
    assert url == "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode()


@pytest.mark.parametrize("behaviour, reason", [("refusal", "refusal"),
                                               ("malformed", "bad_response")])
def test_refusal_and_malformed_are_typed_failures(server, behaviour, reason):
    server.set(behaviour=behaviour)
    with _provider(server) as prov:
        res = prov.get(_query(), timeout_s=10)
    assert not res.ok and res.reason == reason
    assert len(server.requests) == 1  # neither is retried


def test_500_is_retried_with_backoff_then_succeeds(server):
    server.set(behaviour="500", fail_times=2)
    with _provider(server, backoff_s=0.1) as prov:
        res = prov.get(_query(), timeout_s=10)
    assert res.ok and res.extra["attempts"] == 3
    t = server.request_times
    # jittered exponential back-off: uniform in [d/2, d] with d = 0.1, then 0.2
    assert t[1] - t[0] >= 0.05 - 0.01 and t[2] - t[1] >= 0.1 - 0.01


def test_500_forever_gives_up_after_max_retries(server):
    server.set(behaviour="500")
    with _provider(server, max_retries=2) as prov:
        res = prov.get(_query(), timeout_s=10)
    assert not res.ok and res.reason == "http_500" and res.extra["attempts"] == 3
    assert len(server.requests) == 3


def test_429_honours_retry_after(server):
    server.set(behaviour="429", fail_times=1, retry_after_s=0.6)
    with _provider(server, backoff_s=0.01) as prov:
        res = prov.get(_query(), timeout_s=10)
    assert res.ok and res.extra["attempts"] == 2
    t = server.request_times
    assert t[1] - t[0] >= 0.55  # the server's Retry-After, not the 10 ms back-off


def test_429_forever_reports_http_429(server):
    server.set(behaviour="429", retry_after_s=0.05)
    with _provider(server, max_retries=1) as prov:
        res = prov.get(_query(), timeout_s=10)
    assert res.reason == "http_429" and len(server.requests) == 2


def test_hard_timeout(server):
    server.set(behaviour="hang")
    with _provider(server, timeout_s=0.3, max_retries=1, backoff_s=0.01) as prov:
        res = prov.get(_query(), timeout_s=10)
    assert not res.ok and res.reason == "timeout"
    assert len(server.requests) == 2  # timeouts are retried
    assert res.latency_s < 5.0  # bounded by the per-attempt timeout, not by the server


class TricklingServer:
    """Answers 200 with a long body and then sends a byte every 50 ms: defeats a plain socket
    timeout."""

    def __enter__(self):
        self.lsock = socket.create_server(("127.0.0.1", 0))
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()
        self.base_url = f"http://127.0.0.1:{self.lsock.getsockname()[1]}/v1"
        return self

    def _serve(self):
        conn, _ = self.lsock.accept()
        with conn:
            conn.recv(65536)
            conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Length: 100000\r\n\r\n")
            while not self.stop.wait(0.05):
                try:
                    conn.sendall(b" ")
                except OSError:
                    return

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(timeout=5)
        self.lsock.close()


def test_hard_timeout_holds_against_a_trickling_server():
    with TricklingServer() as srv:
        prov = create_prior_provider("openai", {"base_url": srv.base_url, "timeout_s": 0.4,
                                                "max_retries": 0})
        with prov:
            res = prov.get(_query(), timeout_s=20)
    assert res.reason == "timeout" and res.latency_s < 5.0


def test_hard_timeout_holds_when_the_connection_opens_after_the_deadline(monkeypatch):
    """A slow connect (DNS, addresses tried in turn) outlives the deadline while there is no
    socket for the watchdog to shut: the attempt must still end at its deadline, not send its
    request to a server that then trickles for ever."""
    real = socket.create_connection

    def slow_connect(*args, **kwargs):
        time.sleep(1.0)
        return real(*args, **kwargs)

    monkeypatch.setattr(socket, "create_connection", slow_connect)
    with TricklingServer() as srv:
        prov = create_prior_provider("openai", {"base_url": srv.base_url, "timeout_s": 0.4,
                                                "max_retries": 0})
        with prov:
            res = prov.get(_query(), timeout_s=10)
    assert res.reason == "timeout" and res.latency_s < 5.0, (res.reason, res.latency_s)


def test_request_returns_at_once_and_cancel_aborts(server):
    server.set(behaviour="hang")
    prov = _provider(server, timeout_s=30.0, max_retries=0, max_concurrency=1)
    try:
        fut = prov.request(_query())
        assert not fut.done()  # the caller is never blocked by the network
        deadline = time.monotonic() + 5
        while not server.requests and time.monotonic() < deadline:
            time.sleep(0.01)
        assert fut.cancel() and fut.cancelled()
        # the only worker is free again: the socket of the hung call was shut down
        server.set(behaviour="ok")
        assert prov.get(_query(), timeout_s=10).ok
    finally:
        prov.close()


def test_close_resolves_pending_requests_as_cancelled(server):
    server.set(behaviour="hang")
    prov = _provider(server, timeout_s=30.0, max_concurrency=1)
    futs = [prov.request(_query()) for _ in range(3)]  # one in flight, two queued
    prov.close()
    results = [f.result(timeout=5) for f in futs]
    assert [r.reason for r in results] == ["cancelled"] * 3
    assert prov.request(_query()).result(timeout=1).reason == "cancelled"


def test_min_interval_rate_limit(server):
    with _provider(server, min_interval_s=0.15, max_concurrency=3) as prov:
        futs = [prov.request(_query(color=(i, i, i))) for i in range(3)]
        assert all(f.result(timeout=10).ok for f in futs)
    # times as the server received them: the client spaces its sends 0.15 s apart, and the
    # receive times carry the machine's scheduling jitter (tens of ms on a loaded CI box);
    # without the limit the three requests arrive within a few ms
    t = sorted(server.request_times)
    assert min(b - a for a, b in zip(t, t[1:])) >= 0.08 and t[-1] - t[0] >= 0.25


def test_cache_avoids_paying_twice_and_holds_no_secret(server, tmp_path, caplog):
    caplog.set_level(logging.DEBUG, logger="vlm_vpr_ros")
    with _provider(server, cache_dir=str(tmp_path / "cache")) as prov:
        first = prov.get(_query(), timeout_s=10)
        server.set(behaviour="500")  # a second network call would now fail
        second = prov.get(_query(), timeout_s=10)
    assert first.ok and second.ok and len(server.requests) == 1
    assert not first.extra["cached"] and second.extra["cached"]
    assert (second.prior.lat, second.prior.lon) == (first.prior.lat, first.prior.lon)
    files = list((tmp_path / "cache").rglob("*.json"))
    assert len(files) == 1
    entry = json.loads(files[0].read_text())
    assert entry["model"] == "fixture-vlm" and entry["prompt"] == "ltm-v1"
    assert SECRET not in files[0].read_text() and SECRET not in files[0].name
    assert SECRET not in caplog.text and SECRET not in repr(prov) + repr(prov.client)
    assert SECRET not in json.dumps([first.extra, second.extra, first.raw_text])
    # another model or prompt version is another key
    with _provider(server, cache_dir=str(tmp_path / "cache"), model="other") as prov:
        assert prov.get(_query(), timeout_s=10).reason == "http_500"


def test_unreachable_endpoint_is_a_typed_failure():
    prov = create_prior_provider("openai", {"base_url": "http://127.0.0.1:9/v1",
                                            "max_retries": 1, "backoff_s": 0.01})
    with prov:
        res = prov.get(_query(), timeout_s=10)
    assert res.reason == "connection_error" and res.extra["attempts"] == 2


def test_bad_query_images_are_typed_failures(server):
    with _provider(server) as prov:
        assert prov.get(PriorQuery(key="x"), timeout_s=5).reason == "no_image"
        assert prov.get(PriorQuery(encoded=b"not an image"), timeout_s=5).reason == "bad_image"
        bad = np.zeros((4, 4), np.uint8)
        assert prov.get(PriorQuery(image=bad), timeout_s=5).reason == "bad_image"
    assert not server.requests


def test_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="api_key_env"):
        create_prior_provider("openai", {"api_kye_env": "X"})
    with pytest.raises(ConfigError, match="robust"):
        create_prior_provider("openai", {"parser": "fuzzy"})
    with pytest.raises(ConfigError, match="ltm"):
        create_prior_provider("openai", {"prompt": "nope"})
    with pytest.raises(ConfigError, match="http"):
        create_prior_provider("openai", {"base_url": "ftp://x"})
    with pytest.raises(PriorError, match="api_key_file"):
        create_prior_provider("openai", {"api_key_file": str(tmp_path / "missing")})
    key = tmp_path / "key"
    key.write_text(SECRET + "\n")
    prov = create_prior_provider("openai", {"api_key_file": str(key)})
    assert SECRET not in repr(prov.client) and "key=set" in repr(prov.client)
    prov.close()


def test_caller_side_timeout_is_labelled_with_the_model(server):
    server.set(behaviour="slow", delay_s=3.0)
    with _provider(server) as prov:
        res = prov.get(_query(), timeout_s=0.2)  # the caller gives up; the call is aborted
    assert res.reason == "timeout" and res.source == "openai:fixture-vlm"
