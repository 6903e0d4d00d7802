"""TEST FIXTURE: a loopback OpenAI-compatible chat-completions server for the VLM client tests.

This is not part of the package and never talks to a real model. It answers
``POST /v1/chat/completions`` on 127.0.0.1 (ephemeral port) with canned behaviours so that the
client's retries, back-off, timeouts, rate limiting, cache and cancellation can be verified over
real HTTP::

    with ChatServer(behaviour="429", fail_times=2, retry_after_s=0.2) as srv:
        provider = create_prior_provider("openai", {"base_url": srv.base_url, ...})
        ...
        assert len(srv.requests) == 3

Behaviours: ``ok`` (JSON answer with the configured lat/lon), ``slow`` (the same after
``delay_s``), ``429`` / ``500`` (that status, with ``Retry-After`` for 429, for the first
``fail_times`` requests, then ok; ``fail_times=0`` = always), ``malformed`` (a broken JSON body),
``refusal`` (a real-style "I'm unable to provide location details" text), ``fenced`` (a fenced
JSON answer), ``prose`` (coordinates in running text), ``hang`` (never answers until stopped).
Misbehaviours for the fault suite: ``garbage`` (200 with non-JSON bytes), ``huge`` (a 50 MB body,
streamed in 1 MB blocks), ``drip`` (headers, then one byte every ``delay_s``, at most 600 bytes),
``reset`` (the connection is reset without an answer), ``silence`` (the request is read, then
nothing is sent until stopped: same as ``hang``), ``echo`` (the answer text is the request
headers, as a careless proxy or debug server would send them), ``text`` (the answer is
``content``, set with :meth:`ChatServer.set`), ``length`` (no text, ``finish_reason:
"length"``: a reasoning model that spent its token limit on hidden reasoning). Every loop is
bounded and stops with the server.

Dialects (``dialect=``), each with the routes, auth and error bodies of the real server
(tests/chat_dialects.py): ``openai`` (default), ``openai_reasoning`` (rejects ``max_tokens``
and any ``temperature`` but 1, like OpenAI's o-series and gpt-5 models), ``azure`` (a
deployment route, ``api-version`` query, ``api-key`` header), ``ollama`` and ``vllm`` (their
OpenAI-compatible ``/v1`` routes). ``api_key=`` makes the server demand that key;
``structured=`` says what it does with ``response_format`` (``True`` honours it, ``False``
refuses it with a 400, ``"ignore"`` answers in prose anyway); ``tls=(cert, key)`` serves https.
The server counts TCP connections (:attr:`ChatServer.connections`); ``keep_alive=False``
closes each connection after its answer without announcing it (as an idle timeout would).
"""

from __future__ import annotations

import http.server
import json
import ssl
import threading
import time
from typing import Any

from chat_dialects import DIALECTS, body_problem, route_problem, structured_answer

BEHAVIOURS = ("ok", "slow", "429", "500", "malformed", "refusal", "fenced", "prose", "hang",
              "garbage", "huge", "drip", "reset", "silence", "echo", "text", "length")
HUGE_BYTES = 50 * 1024 * 1024


class _Handler(http.server.BaseHTTPRequestHandler):
    server: "_Server"
    protocol_version = "HTTP/1.1"

    def setup(self) -> None:
        self.server.owner._on_connection()
        if isinstance(self.request, ssl.SSLSocket):  # TLS handshake in this thread
            self.request.settimeout(10.0)
            try:
                self.request.do_handshake()
            except (OSError, ssl.SSLError):
                self.request.close()
        super().setup()

    def handle(self) -> None:
        try:
            super().handle()
        except (OSError, ssl.SSLError):
            pass  # a client that went away or spoke no TLS: fine for a fixture

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - silence stderr
        pass

    def do_GET(self) -> None:  # noqa: N802 - http.server naming
        if self.path.rstrip("/").endswith("/models"):
            self._send(200, {"object": "list", "data": [{"id": "fixture-model"}]})
        else:
            self._send(404, {"error": {"message": "not found"}})

    def do_POST(self) -> None:  # noqa: N802 - http.server naming
        length = int(self.headers.get("Content-Length") or 0)
        raw = self.rfile.read(length) if length else b""
        owner = self.server.owner
        headers = dict(self.headers.items())
        problem = route_problem(owner.dialect, self.path, headers, owner.api_key,
                                owner.deployment)
        if problem is not None:
            self._send(*problem)
            return
        try:
            body = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            self._send(400, {"error": {"message": "request body is not JSON"}})
            return
        problem = body_problem(owner.dialect, body, owner.models, owner.structured)
        if problem is not None:
            owner._record(body, headers, rejected=True)
            self._send(*problem)
            return
        owner._on_request(self, body, headers)

    def _send(self, status: int, payload: Any, headers: dict[str, str] | None = None,
              raw: bytes | None = None) -> None:
        data = raw if raw is not None else json.dumps(payload).encode("utf-8")
        try:
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            for key, value in (headers or {}).items():
                self.send_header(key, value)
            self.end_headers()
            self.wfile.write(data)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the client gave up (timeout/cancel): fine for a fixture
        if not self.server.owner.keep_alive:  # close without saying so (an idle timeout)
            self.close_connection = True


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True
    owner: "ChatServer"


def completion(content: str, model: str = "fixture-model", finish: str = "stop",
               dialect: str = "openai") -> dict[str, Any]:
    """A minimal chat-completions response body carrying ``content``."""
    body = {
        "id": "chatcmpl-fixture", "object": "chat.completion", "created": int(time.time()),
        "model": model,
        "choices": [{"index": 0, "finish_reason": finish,
                     "message": {"role": "assistant", "content": content}}],
        "usage": {"prompt_tokens": 1, "completion_tokens": 1, "total_tokens": 2},
    }
    if dialect == "ollama":
        body["system_fingerprint"] = "fp_ollama"
    return body


class ChatServer:
    """Loopback chat-completions server (test fixture). Use as a context manager."""

    def __init__(self, behaviour: str = "ok", lat: float = 48.8584, lon: float = 2.2945,
                 delay_s: float = 0.0, retry_after_s: float = 1.0, fail_times: int = 0,
                 dialect: str = "openai", api_key: str | None = None,
                 models: tuple[str, ...] | None = None, deployment: str = "gpt-5-mini",
                 structured: bool | str = True, tls: tuple[str, str] | None = None,
                 uncertainty_km: float = 25.0, keep_alive: bool = True) -> None:
        if dialect not in DIALECTS:
            raise ValueError(f"unknown dialect {dialect!r}; choices: {DIALECTS}")
        self.dialect, self.api_key, self.models = dialect, api_key, models
        self.deployment, self.structured, self.tls = deployment, structured, tls
        self.uncertainty_km = uncertainty_km
        self.keep_alive = keep_alive
        self.content = ""
        self._connections = 0
        self._rejected: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._requests: list[dict[str, Any]] = []
        self._times: list[float] = []
        self._headers: list[dict[str, str]] = []
        self._failures = 0
        self.behaviour = "ok"
        self.lat, self.lon = lat, lon
        self.delay_s = delay_s
        self.retry_after_s = retry_after_s
        self.fail_times = fail_times
        self.set(behaviour=behaviour)
        self._httpd: _Server | None = None
        self._thread: threading.Thread | None = None

    # --- lifecycle -------------------------------------------------------------------------
    def start(self) -> "ChatServer":
        if self._httpd is not None:
            return self
        self._stop.clear()
        self._httpd = _Server(("127.0.0.1", 0), _Handler)
        self._httpd.owner = self
        if self.tls is not None:
            ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            ctx.load_cert_chain(*self.tls)
            self._httpd.socket = ctx.wrap_socket(self._httpd.socket, server_side=True,
                                                 do_handshake_on_connect=False)
        self._thread = threading.Thread(target=self._httpd.serve_forever,
                                        kwargs={"poll_interval": 0.05},
                                        name="chat-fixture", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()  # releases "hang" and "slow" handlers
        if self._httpd is not None:
            self._httpd.shutdown()
            self._httpd.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._httpd, self._thread = None, None

    def __enter__(self) -> "ChatServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- configuration and inspection --------------------------------------------------------
    @property
    def port(self) -> int:
        if self._httpd is None:
            raise RuntimeError("ChatServer is not started")
        return int(self._httpd.server_address[1])

    @property
    def base_url(self) -> str:
        """The URL a user would configure: ``.../v1``, or for ``azure`` the deployment's
        chat-completions URL with its ``api-version``."""
        return self.url_for("127.0.0.1")

    def url_for(self, host: str, api_version: str = "2024-10-21") -> str:
        scheme = "https" if self.tls else "http"
        if self.dialect == "azure":
            return (f"{scheme}://{host}:{self.port}/openai/deployments/{self.deployment}"
                    f"/chat/completions?api-version={api_version}")
        return f"{scheme}://{host}:{self.port}/v1"

    @property
    def connections(self) -> int:
        """TCP connections accepted so far."""
        with self._lock:
            return self._connections

    @property
    def rejected(self) -> list[dict[str, Any]]:
        """Bodies refused by the dialect's checks (400/404), in order."""
        with self._lock:
            return list(self._rejected)

    @property
    def requests(self) -> list[dict[str, Any]]:
        """Bodies of the chat-completions requests received so far (a copy)."""
        with self._lock:
            return list(self._requests)

    @property
    def request_headers(self) -> list[dict[str, str]]:
        """HTTP headers of each chat-completions request (e.g. to check Authorization)."""
        with self._lock:
            return list(self._headers)

    @property
    def request_times(self) -> list[float]:
        """``time.monotonic()`` at the arrival of each request (for back-off/rate checks)."""
        with self._lock:
            return list(self._times)

    def set(self, behaviour: str | None = None, delay_s: float | None = None,
            lat: float | None = None, lon: float | None = None,
            retry_after_s: float | None = None, fail_times: int | None = None,
            content: str | None = None) -> None:
        """Change behaviour at runtime; ``fail_times`` changes reset the failure counter."""
        with self._lock:
            if content is not None:
                self.content = content
            if behaviour is not None:
                if behaviour not in BEHAVIOURS:
                    raise ValueError(f"unknown behaviour {behaviour!r}; choices: {BEHAVIOURS}")
                self.behaviour = behaviour
                self._failures = 0
            if delay_s is not None:
                self.delay_s = delay_s
            if lat is not None:
                self.lat = lat
            if lon is not None:
                self.lon = lon
            if retry_after_s is not None:
                self.retry_after_s = retry_after_s
            if fail_times is not None:
                self.fail_times = fail_times
                self._failures = 0

    # --- request handling ------------------------------------------------------------------
    def _on_connection(self) -> None:
        with self._lock:
            self._connections += 1

    def _record(self, body: dict[str, Any], headers: dict[str, str],
                rejected: bool = False) -> None:
        with self._lock:
            (self._rejected if rejected else self._requests).append(body)
            if not rejected:
                self._headers.append(headers)
                self._times.append(time.monotonic())

    def _on_request(self, handler: _Handler, body: dict[str, Any],
                    headers: dict[str, str]) -> None:
        self._record(body, headers)
        with self._lock:
            behaviour, lat, lon = self.behaviour, self.lat, self.lon
            delay, retry_after = self.delay_s, self.retry_after_s
            failing = False
            if behaviour in ("429", "500"):
                failing = self.fail_times == 0 or self._failures < self.fail_times
                if failing:
                    self._failures += 1
        model = str(body.get("model", "fixture-model"))
        answer = json.dumps({"latitude": lat, "longitude": lon})
        schema = (body.get("response_format") or {}).get("json_schema")
        if behaviour == "ok" and schema and self.structured is True:
            handler._send(200, completion(
                structured_answer(schema, lat, lon, self.uncertainty_km), model,
                dialect=self.dialect))
            return
        if behaviour == "ok" and schema and self.structured == "ignore":
            behaviour = "prose"
        if behaviour in ("hang", "silence"):
            self._stop.wait()
            return
        if behaviour in ("garbage", "huge", "drip", "reset"):
            self._misbehave(handler, behaviour, delay)
            return
        if behaviour == "slow" and self._stop.wait(delay):
            return
        if behaviour == "429" and failing:
            handler._send(429, {"error": {"message": "rate limited", "type": "rate_limit"}},
                          headers={"Retry-After": f"{retry_after:g}"})
        elif behaviour == "500" and failing:
            handler._send(500, {"error": {"message": "internal error"}})
        elif behaviour == "malformed":
            handler._send(200, None, raw=b'{"id": "chatcmpl-x", "choices": [{"message": {')
        elif behaviour == "refusal":
            handler._send(200, completion(
                "I'm unable to provide location details based on this image.", model))
        elif behaviour == "fenced":
            handler._send(200, completion(f"```json\n{answer}\n```", model))
        elif behaviour == "prose":
            handler._send(200, completion(
                f"This looks like central Paris. My best estimate is latitude {lat}, "
                f"longitude {lon}.", model, dialect=self.dialect))
        elif behaviour == "echo":
            handler._send(200, completion("Request headers:\n" + "\n".join(
                f"{k}: {v}" for k, v in headers.items()), model, dialect=self.dialect))
        elif behaviour == "text":
            handler._send(200, completion(self.content, model, dialect=self.dialect))
        elif behaviour == "length":
            handler._send(200, completion("", model, finish="length", dialect=self.dialect))
        else:
            handler._send(200, completion(answer, model, dialect=self.dialect))

    def _misbehave(self, handler: _Handler, behaviour: str, delay: float) -> None:
        import socket
        import struct

        try:
            if behaviour == "garbage":
                handler._send(200, None, raw=b"\x00\xff<html>502 Bad Gateway</html>\x9c" * 40)
            elif behaviour == "reset":  # SO_LINGER 0: close() sends RST
                handler.connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                              struct.pack("ii", 1, 0))
                handler.connection.close()
                handler.close_connection = True
            elif behaviour == "huge":
                handler.send_response(200)
                handler.send_header("Content-Type", "application/json")
                handler.send_header("Content-Length", str(HUGE_BYTES))
                handler.end_headers()
                block = b"[" * (1 << 20)
                for _ in range(HUGE_BYTES // len(block)):
                    if self._stop.is_set():
                        break
                    handler.wfile.write(block)
            elif behaviour == "drip":
                handler.send_response(200)
                handler.send_header("Content-Type", "application/json")
                handler.send_header("Content-Length", "600")
                handler.end_headers()
                for _ in range(600):
                    if self._stop.wait(max(delay, 0.05)):
                        break
                    handler.wfile.write(b" ")
                    handler.wfile.flush()
        except OSError:
            pass  # the client gave up: expected
