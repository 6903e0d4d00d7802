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
nothing is sent until stopped: same as ``hang``). Every loop is bounded and stops with the
server.
"""

from __future__ import annotations

import http.server
import json
import threading
import time
from typing import Any

BEHAVIOURS = ("ok", "slow", "429", "500", "malformed", "refusal", "fenced", "prose", "hang",
              "garbage", "huge", "drip", "reset", "silence")
HUGE_BYTES = 50 * 1024 * 1024


class _Handler(http.server.BaseHTTPRequestHandler):
    server: "_Server"
    protocol_version = "HTTP/1.1"

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
        if not self.path.rstrip("/").endswith("/chat/completions"):
            self._send(404, {"error": {"message": f"no route {self.path}"}})
            return
        try:
            body = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            self._send(400, {"error": {"message": "request body is not JSON"}})
            return
        self.server.owner._on_request(self, body, dict(self.headers.items()))

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


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True
    owner: "ChatServer"


def completion(content: str, model: str = "fixture-model") -> dict[str, Any]:
    """A minimal chat-completions response body carrying ``content``."""
    return {
        "id": "chatcmpl-fixture", "object": "chat.completion", "created": int(time.time()),
        "model": model,
        "choices": [{"index": 0, "finish_reason": "stop",
                     "message": {"role": "assistant", "content": content}}],
        "usage": {"prompt_tokens": 1, "completion_tokens": 1, "total_tokens": 2},
    }


class ChatServer:
    """Loopback chat-completions server (test fixture). Use as a context manager."""

    def __init__(self, behaviour: str = "ok", lat: float = 48.8584, lon: float = 2.2945,
                 delay_s: float = 0.0, retry_after_s: float = 1.0, fail_times: int = 0) -> None:
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
        return f"http://127.0.0.1:{self.port}/v1"

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
            retry_after_s: float | None = None, fail_times: int | None = None) -> None:
        """Change behaviour at runtime; ``fail_times`` changes reset the failure counter."""
        with self._lock:
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
    def _on_request(self, handler: _Handler, body: dict[str, Any],
                    headers: dict[str, str]) -> None:
        with self._lock:
            self._requests.append(body)
            self._headers.append(headers)
            self._times.append(time.monotonic())
            behaviour, lat, lon = self.behaviour, self.lat, self.lon
            delay, retry_after = self.delay_s, self.retry_after_s
            failing = False
            if behaviour in ("429", "500"):
                failing = self.fail_times == 0 or self._failures < self.fail_times
                if failing:
                    self._failures += 1
        model = str(body.get("model", "fixture-model"))
        answer = json.dumps({"latitude": lat, "longitude": lon})
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
                f"longitude {lon}.", model))
        else:
            handler._send(200, completion(answer, model))

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
