"""The VLM client's connections: kept alive and reused (counted by the loopback server), a
kept connection the server dropped is replaced without costing an attempt, the deadline and
abort still hold on a reused connection; https through an authenticating CONNECT proxy; a TLS
error named as such. The canary run: one `localize` through the proxy to an https Azure-style
endpoint, and neither the key nor the proxy password in any output."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from chat_server import ChatServer
from connect_proxy import ConnectProxy, self_signed

from vlm_vpr_ros.priors import PriorQuery, create_prior_provider

KEY = "sk-transport-canary-9876543210abcdefQ"
PROXY_USER, PROXY_PW = "robot7", "proxy-canary-pw-5550123"


def _query(i: int = 0) -> PriorQuery:
    img = np.zeros((32, 48, 3), np.uint8)
    img[:, : 1 + i % 47] = 180
    return PriorQuery(image=img)


def _provider(url: str, **kw):
    return create_prior_provider("openai", {"base_url": url, "model": "m", "max_retries": 0,
                                            "timeout_s": 10.0, "api_key_env": "VLM_NO_KEY",
                                            **kw})


@pytest.fixture(scope="module")
def cert(tmp_path_factory):
    pair = self_signed(tmp_path_factory.mktemp("tls"), "vlm.test")
    if pair is None:
        pytest.skip("the openssl command is needed to make a test certificate")
    return pair


def test_100_sequential_requests_reuse_one_connection():
    with ChatServer() as srv, _provider(srv.base_url) as prov:
        results = [prov.get(_query(i), timeout_s=10) for i in range(100)]
        n, opened = srv.connections, prov.client.pool.opened
    assert all(r.ok and r.extra["attempts"] == 1 for r in results)
    print(f"\n100 sequential requests to one endpoint: {n} TCP connection(s) "
          f"(client opened {opened})")
    assert n <= 2 and opened == n


def test_a_connection_dropped_by_the_server_is_replaced_for_free():
    with ChatServer(keep_alive=False) as srv, _provider(srv.base_url) as prov:
        results = [prov.get(_query(i), timeout_s=10) for i in range(5)]
        assert srv.connections == 5  # each idle connection found closed and replaced
    assert all(r.ok and r.extra["attempts"] == 1 for r in results)


def test_a_stale_connection_that_looks_alive_is_retried_once(monkeypatch):
    """The server closes the kept connection just after the liveness check: the request
    fails on it before any answer, and goes again on a new connection (same attempt)."""
    import vlm_vpr_ros.priors.transport as transport

    monkeypatch.setattr(transport, "_dropped", lambda conn: False)
    with ChatServer(keep_alive=False) as srv, _provider(srv.base_url) as prov:
        results = [prov.get(_query(i), timeout_s=10) for i in range(4)]
        assert len(srv.requests) == 4 and srv.connections == 4
    assert all(r.ok and r.extra["attempts"] == 1 for r in results)


def test_deadline_and_abort_hold_on_a_kept_connection():
    with ChatServer() as srv, _provider(srv.base_url, timeout_s=0.5) as prov:
        assert prov.get(_query(), timeout_s=10).ok  # the connection is now kept
        srv.set(behaviour="hang")
        t0 = time.monotonic()
        res = prov.get(_query(1), timeout_s=10)
        assert res.reason == "timeout" and time.monotonic() - t0 < 3.0
        srv.set(behaviour="ok")
        assert prov.get(_query(2), timeout_s=10).ok
        srv.set(behaviour="hang")
        fut = prov.request(_query(3))
        deadline = time.monotonic() + 5
        while len(srv.requests) < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert fut.cancel()
        srv.set(behaviour="ok")
        assert prov.get(_query(4), timeout_s=10).ok  # the aborted connection was not reused
        assert srv.connections == 3  # ok kept; the timed-out and aborted ones not reused


def test_https_through_an_authenticating_connect_proxy(cert, monkeypatch):
    with ChatServer(tls=cert, api_key=KEY) as srv, \
            ConnectProxy(srv.port, PROXY_USER, PROXY_PW) as proxy:
        monkeypatch.setenv("https_proxy", proxy.url)
        monkeypatch.setenv("VLM_T_KEY", KEY)
        monkeypatch.delenv("no_proxy", raising=False)
        monkeypatch.delenv("NO_PROXY", raising=False)
        url = srv.url_for("vlm.test")
        with _provider(url, ca_file=cert[0], api_key_env="VLM_T_KEY") as prov:
            results = [prov.get(_query(i), timeout_s=10) for i in range(10)]
        assert all(r.ok and r.extra["attempts"] == 1 for r in results)
        assert proxy.connects == [f"vlm.test:{srv.port}"] and proxy.refused == 0  # one tunnel
        assert "Proxy-Authorization" not in srv.request_headers[0]  # for the proxy only
        with _provider(url, api_key_env="VLM_T_KEY") as prov:  # not the test CA: refused
            assert prov.get(_query(), timeout_s=10).reason == "tls_error"
        monkeypatch.setenv("https_proxy", proxy.url.replace(PROXY_PW, "wrong"))
        with _provider(url, ca_file=cert[0], api_key_env="VLM_T_KEY", max_retries=2) as prov:
            res = prov.get(_query(), timeout_s=10)
        assert res.reason == "proxy_auth" and proxy.refused == 1  # not retried


def test_http_endpoint_through_the_proxy(monkeypatch):
    with ChatServer() as srv, ConnectProxy(srv.port, PROXY_USER, PROXY_PW) as proxy:
        monkeypatch.setenv("http_proxy", proxy.url)
        monkeypatch.delenv("no_proxy", raising=False)
        monkeypatch.delenv("NO_PROXY", raising=False)
        with _provider(srv.url_for("vlm.test")) as prov:
            assert prov.get(_query(), timeout_s=10).ok
        assert proxy.forwards and proxy.forwards[0].startswith(
            f"POST http://vlm.test:{srv.port}/v1/chat/completions")


def test_https_url_to_a_plain_http_server_is_a_tls_error(caplog):
    with ChatServer() as srv, _provider(srv.base_url.replace("http:", "https:"),
                                        max_retries=2) as prov:
        res = prov.get(_query(), timeout_s=10)
    assert res.reason == "tls_error" and res.extra["attempts"] == 1  # not retried
    lines = [r.getMessage() for r in caplog.records if "TLS" in r.getMessage()]
    assert len(lines) == 1 and "http://" in lines[0] and "\n" not in lines[0]


def test_canary_localize_through_the_proxy(cert, demo_map, demo_data, tmp_path):
    """Every output of a verbose `localize` run with live priors: stdout, stderr (-vv: debug
    logs), the results CSV and the answer cache hold neither the key nor the proxy password
    (nor its Basic token)."""
    import base64

    names = sorted(p.name for p in (demo_data / "images").iterdir())[:3]
    queries = tmp_path / "q.csv"
    queries.write_text("file\n" + "\n".join(names) + "\n")
    out, cache = tmp_path / "res.csv", tmp_path / "cache"
    with ChatServer(dialect="azure", api_key=KEY, tls=cert) as srv, \
            ConnectProxy(srv.port, PROXY_USER, PROXY_PW) as proxy:
        env = {**os.environ, "https_proxy": proxy.url, "VLM_T_KEY": KEY, "no_proxy": "",
               "NO_PROXY": ""}
        proc = subprocess.run(
            [sys.executable, "-m", "vlm_vpr_ros.cli", "-vv", "localize", "--map", demo_map,
             "--images", demo_data / "images", "--queries", queries, "--out", out,
             "--prior", "openai", "--prior-option", f"base_url={srv.url_for('vlm.test')}",
             "--prior-option", "model=gpt-5-mini", "--prior-option", "api_key_env=VLM_T_KEY",
             "--prior-option", f"ca_file={cert[0]}", "--prior-option", f"cache_dir={cache}",
             "--prior-option", "structured_output=true"],
            capture_output=True, text=True, timeout=300, env=env)
        tunnels = len(proxy.connects)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 3 and all(r["prior_source"] == "openai:gpt-5-mini"
                                  and r["prior_reason"] == "" and r["prior_parse"] == "structured"
                                  for r in rows), rows
    assert 1 <= tunnels <= 3  # localize asks ahead: at most one tunnel per request in flight
    token = base64.b64encode(f"{PROXY_USER}:{PROXY_PW}".encode()).decode()
    texts = [proc.stdout, proc.stderr, out.read_text(),
             *(p.read_text() for p in cache.rglob("*.json"))]
    assert len(texts) == 6 and "DEBUG" in proc.stderr
    for text in texts:
        for canary in (KEY, PROXY_PW, token):
            assert canary not in text
