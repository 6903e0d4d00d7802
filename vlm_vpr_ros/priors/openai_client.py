"""A small, dependable client of OpenAI-compatible ``/chat/completions`` endpoints (OpenAI,
Gemini's OpenAI-compatible endpoint, Ollama, vLLM, llama.cpp server), stdlib only.

:meth:`ChatClient.call` is blocking and is meant to run in a worker thread; it never raises on
network or server trouble and returns a :class:`ChatReply` instead. It implements

* a hard per-attempt timeout (a watchdog closes the socket, so even a server that trickles
  bytes cannot hold a caller longer than ``timeout_s``),
* bounded retries with exponential back-off and jitter on timeouts, connection errors, 408 and
  5xx; ``429`` (and ``503``) honour ``Retry-After`` (seconds or an HTTP date),
* a minimum interval between the starts of any two requests (shared by all threads),
* cancellation: :meth:`CallHandle.abort` wakes a sleeping retry and shuts the socket down.

The API key goes into the ``Authorization`` header only: it is never logged, never part of
``repr`` and never returned.
"""

from __future__ import annotations

import email.utils
import http.client
import json
import logging
import random
import socket
import ssl
import threading
import time
import urllib.parse
import urllib.request
from dataclasses import dataclass
from typing import Any

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.redact import redact, register_secret

log = logging.getLogger(__name__)

MAX_RESPONSE_BYTES = 8 * 1024 * 1024
_LOOPBACK = ("127.", "localhost", "::1", "[::1]")


@dataclass(frozen=True)
class ChatReply:
    """Outcome of one chat call: ``content`` when ``reason == ""``."""

    content: str | None
    reason: str = ""  # "", "timeout", "http_429", "http_500", "connection_error", ...
    status: int | None = None
    attempts: int = 0
    refusal: str | None = None  # the API's structured refusal text, when it sends one

    @property
    def ok(self) -> bool:
        return not self.reason


class CallHandle:
    """Cancellation token of one :meth:`ChatClient.call`."""

    def __init__(self) -> None:
        self.aborted = threading.Event()
        self._lock = threading.Lock()
        self._conn: http.client.HTTPConnection | None = None

    def _attach(self, conn: http.client.HTTPConnection | None) -> None:
        with self._lock:
            self._conn = conn
        if conn is not None and self.aborted.is_set():
            _shutdown(conn)

    def abort(self) -> None:
        """Stop the call: wake its back-off sleep and shut its socket down (idempotent)."""
        self.aborted.set()
        with self._lock:
            conn = self._conn
        if conn is not None:
            _shutdown(conn)


def _shutdown(conn: http.client.HTTPConnection) -> None:
    sock = conn.sock
    if sock is not None:
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass  # already closed


def parse_retry_after(value: str | None, now: float | None = None) -> float | None:
    """Seconds to wait from a ``Retry-After`` header (delta-seconds or an HTTP date)."""
    if not value:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError, IndexError):
        return None
    if when is None:
        return None
    return max(0.0, when.timestamp() - (time.time() if now is None else now))


class ChatClient:
    """Blocking chat-completions client with retries, rate limiting, timeouts and aborts."""

    def __init__(self, base_url: str, api_key: str | None = None, timeout_s: float = 60.0,
                 max_retries: int = 3, backoff_s: float = 1.0, max_backoff_s: float = 30.0,
                 max_retry_after_s: float = 120.0, min_interval_s: float = 0.0,
                 rng: random.Random | None = None) -> None:
        try:
            url = urllib.parse.urlsplit(str(base_url).strip())
            url.port  # noqa: B018 - raises ValueError on a bad port
        except ValueError:
            url = None
        if url is None or url.scheme not in ("http", "https") or not url.hostname:
            raise ConfigError(f"base_url must be an http(s) URL, got {redact(base_url)!r}")
        if timeout_s <= 0 or max_retries < 0 or backoff_s < 0 or min_interval_s < 0:
            raise ConfigError("timeout_s must be > 0; max_retries, backoff_s and "
                              "min_interval_s must be >= 0")
        register_secret(url.password)  # never log a key given as URL userinfo
        register_secret(url.username)
        self._url = url
        self._path = f"{url.path.rstrip('/')}/chat/completions"
        host = url.hostname or ""
        host = f"[{host}]" if ":" in host else host
        #: the URL as logged: no userinfo
        self.endpoint = f"{url.scheme}://{host}{f':{url.port}' if url.port else ''}{self._path}"
        self.__api_key = api_key or None
        self.timeout_s = float(timeout_s)
        self.max_retries = int(max_retries)
        self.backoff_s = float(backoff_s)
        self.max_backoff_s = float(max_backoff_s)
        self.max_retry_after_s = float(max_retry_after_s)
        self.min_interval_s = float(min_interval_s)
        self._rng = rng or random.Random()
        self._slot_lock = threading.Lock()
        self._next_slot = 0.0

    def __repr__(self) -> str:
        return f"ChatClient({self.endpoint!r}, key={'set' if self.__api_key else 'none'})"

    # --- public ----------------------------------------------------------------------------
    def call(self, body: dict[str, Any], handle: CallHandle | None = None) -> ChatReply:
        """POST ``body``; retry per policy; never raises on network/server trouble."""
        handle = handle or CallHandle()
        data = json.dumps(body).encode("utf-8")
        reply = ChatReply(None, "cancelled")
        for attempt in range(self.max_retries + 1):
            if not self._wait(self._reserve_slot(), handle):
                return ChatReply(None, "cancelled", attempts=attempt)
            reply, retry_after = self._attempt(data, handle)
            reply = ChatReply(reply.content, reply.reason, reply.status, attempt + 1,
                              reply.refusal)
            if reply.ok or handle.aborted.is_set() or not self._retryable(reply):
                return reply
            if attempt == self.max_retries:
                break
            delay = self._backoff(attempt)
            if retry_after is not None:
                if retry_after > self.max_retry_after_s:
                    log.warning("%s: server asks to retry after %.0f s (> %.0f s): giving up",
                                self.endpoint, retry_after, self.max_retry_after_s)
                    return reply
                delay = retry_after
            log.info("%s: %s (attempt %d/%d), retrying in %.2f s", self.endpoint, reply.reason,
                     attempt + 1, self.max_retries + 1, delay)
            if not self._wait(delay, handle):
                return ChatReply(None, "cancelled", reply.status, attempt + 1)
        return reply

    # --- policy ----------------------------------------------------------------------------
    @staticmethod
    def _retryable(reply: ChatReply) -> bool:
        if reply.reason in ("timeout", "connection_error"):
            return True
        return reply.status is not None and (reply.status in (408, 429) or reply.status >= 500)

    def _backoff(self, attempt: int) -> float:
        """Exponential back-off with jitter: uniform in [d/2, d], d = backoff_s * 2**attempt."""
        d = min(self.max_backoff_s, self.backoff_s * (2.0 ** attempt))
        return d * (0.5 + 0.5 * self._rng.random())

    def _reserve_slot(self) -> float:
        """Seconds to wait so that request starts are at least ``min_interval_s`` apart."""
        with self._slot_lock:
            now = time.monotonic()
            start = max(now, self._next_slot)
            self._next_slot = start + self.min_interval_s
            return start - now

    @staticmethod
    def _wait(seconds: float, handle: CallHandle) -> bool:
        """Sleep unless aborted; False when aborted."""
        if seconds > 0:
            return not handle.aborted.wait(seconds)
        return not handle.aborted.is_set()

    # --- transport -------------------------------------------------------------------------
    def _connection(self) -> tuple[http.client.HTTPConnection, str]:
        url = self._url
        host, port = url.hostname or "", url.port
        path = self._path
        proxy = None
        if not host.startswith(_LOOPBACK) and not urllib.request.proxy_bypass(host):
            proxy = urllib.request.getproxies().get(url.scheme)
        if url.scheme == "https":
            ctx = ssl.create_default_context()
            if proxy:
                p = urllib.parse.urlsplit(proxy)
                conn = http.client.HTTPSConnection(p.hostname or "", p.port or 3128,
                                                   timeout=self.timeout_s, context=ctx)
                conn.set_tunnel(host, port or 443)
            else:
                conn = http.client.HTTPSConnection(host, port, timeout=self.timeout_s,
                                                   context=ctx)
            return conn, path
        if proxy:
            p = urllib.parse.urlsplit(proxy)
            return (http.client.HTTPConnection(p.hostname or "", p.port or 3128,
                                               timeout=self.timeout_s), self.endpoint)
        return http.client.HTTPConnection(host, port, timeout=self.timeout_s), path

    def _attempt(self, data: bytes, handle: CallHandle) -> tuple[ChatReply, float | None]:
        conn, path = self._connection()
        headers = {"Content-Type": "application/json", "Accept": "application/json",
                   "User-Agent": "vlm_vpr_ros"}
        if self.__api_key:
            headers["Authorization"] = f"Bearer {self.__api_key}"
        fired = threading.Event()

        def _expire() -> None:
            fired.set()
            _shutdown(conn)

        watchdog = threading.Timer(self.timeout_s, _expire)
        watchdog.daemon = True
        handle._attach(conn)
        watchdog.start()
        try:
            conn.connect()
            if handle.aborted.is_set():  # aborted before the socket existed
                return ChatReply(None, "cancelled"), None
            conn.request("POST", path, body=data, headers=headers)
            resp = conn.getresponse()
            status = resp.status
            retry_after = parse_retry_after(resp.getheader("Retry-After"))
            payload = resp.read(MAX_RESPONSE_BYTES + 1)
        except ssl.SSLCertVerificationError as exc:
            log.error("%s: TLS certificate problem: %s", self.endpoint, exc)
            return ChatReply(None, "tls_error"), None
        except (OSError, http.client.HTTPException) as exc:
            if handle.aborted.is_set():
                return ChatReply(None, "cancelled"), None
            if fired.is_set() or isinstance(exc, (TimeoutError, socket.timeout)):
                return ChatReply(None, "timeout"), None
            log.debug("%s: %s: %s", self.endpoint, type(exc).__name__, exc)
            return ChatReply(None, "connection_error"), None
        finally:
            watchdog.cancel()
            handle._attach(None)
            conn.close()
        if handle.aborted.is_set():  # the socket was shut down under a read: data is partial
            return ChatReply(None, "cancelled"), None
        if fired.is_set():
            return ChatReply(None, "timeout"), None
        if status != 200:
            if status in (401, 403):  # bodies may echo a masked key: do not log them
                log.error("%s: HTTP %d (check the API key / permissions)", self.endpoint, status)
            else:
                log.debug("%s: HTTP %d: %s", self.endpoint, status, payload[:300])
            return ChatReply(None, f"http_{status}", status), retry_after
        return _read_completion(payload), None


def _read_completion(payload: bytes) -> ChatReply:
    """The assistant text of a chat-completions body, or ``bad_response``."""
    if len(payload) > MAX_RESPONSE_BYTES:
        return ChatReply(None, "bad_response", 200)
    try:
        body = json.loads(payload.decode("utf-8"))
        message = body["choices"][0]["message"]
    except (ValueError, KeyError, IndexError, TypeError, RecursionError):
        return ChatReply(None, "bad_response", 200)
    if not isinstance(message, dict):
        return ChatReply(None, "bad_response", 200)
    refusal = message.get("refusal")
    content = message.get("content")
    if isinstance(content, list):  # content parts
        content = "".join(p.get("text", "") for p in content
                          if isinstance(p, dict) and isinstance(p.get("text"), str))
    if isinstance(refusal, str) and refusal and not content:
        return ChatReply(refusal, "refusal", 200, refusal=refusal)
    if not isinstance(content, str):
        return ChatReply(None, "bad_response", 200)
    return ChatReply(content, "", 200)
