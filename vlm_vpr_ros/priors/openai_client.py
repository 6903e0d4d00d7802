"""A small, dependable client of OpenAI-compatible ``/chat/completions`` endpoints (OpenAI,
Azure OpenAI deployments, Gemini's OpenAI-compatible endpoint, Ollama, vLLM, llama.cpp server),
stdlib only.

Why hand-written rather than the ``openai`` package: a robot needs guarantees that client
does not give. :meth:`ChatClient.call` runs in a worker thread and must be stoppable from the
node's thread at any moment and bounded by a hard deadline even against a server that trickles
one byte at a time; that needs the socket itself (a watchdog and :meth:`CallHandle.abort` shut
it down), which a high-level SDK hides behind its own retry loop and timeouts. The request
spacing is global to all threads, failures are values (never exceptions), and no secret may
reach a log, a ``repr`` or an error text; the whole path is ~600 lines that can be audited.

:meth:`ChatClient.call` never raises on network or server trouble and returns a
:class:`ChatReply` instead. It implements

* a hard per-attempt timeout (a watchdog closes the socket, so even a server that trickles
  bytes cannot hold a caller longer than ``timeout_s``),
* bounded retries with exponential back-off and jitter on timeouts, connection errors, 408 and
  5xx; ``429`` (and ``503``) honour ``Retry-After`` (seconds or an HTTP date),
* a minimum interval between the starts of any two requests (shared by all threads),
* cancellation: :meth:`CallHandle.abort` wakes a sleeping retry and shuts the socket down,
* kept-alive connections, reused across requests (:mod:`~vlm_vpr_ros.priors.transport`): a
  robot asking once a second pays the TCP and TLS handshakes once, not every time; a kept
  connection the server closed meanwhile is replaced without costing an attempt,
* the base URL's query string (Azure ``?api-version=...``), the ``api-key`` header of Azure
  endpoints, and http proxies with credentials (``Proxy-Authorization`` on the CONNECT).

The API key goes into its header only: it is never logged, never part of ``repr`` and never
returned. Bodies of error answers are logged only at debug level, redacted.
"""

from __future__ import annotations

import dataclasses
import email.utils
import http.client
import json
import logging
import random
import socket
import ssl
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.priors.transport import (ConnectionPool, Endpoint, Proxy, make_connection,
                                          request_target)
from vlm_vpr_ros.redact import redact

log = logging.getLogger(__name__)

MAX_RESPONSE_BYTES = 8 * 1024 * 1024


@dataclass(frozen=True)
class ChatReply:
    """Outcome of one chat call: ``content`` when ``reason == ""``."""

    content: str | None
    reason: str = ""  # "", "timeout", "http_429", "http_500", "connection_error", ...
    status: int | None = None
    attempts: int = 0
    refusal: str | None = None  # the API's structured refusal text, when it sends one
    finish_reason: str | None = None  # "stop", "length" (cut at the token limit), ...
    #: the body of an HTTP error answer (read by the caller to explain a 400; never logged
    #: unredacted, never printed)
    error_body: bytes | None = field(default=None, repr=False)
    #: one line saying what was wrong with an answer that is not a completion (redacted)
    detail: str | None = None

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
                 rng: random.Random | None = None, auth_header: str = "auto",
                 ca_file: str | None = None) -> None:
        self._url = Endpoint.parse(base_url, auth_header)
        if not (timeout_s > 0 and max_retries >= 0 and backoff_s >= 0 and min_interval_s >= 0):
            raise ConfigError("timeout_s must be > 0; max_retries, backoff_s and "
                              "min_interval_s must be >= 0")
        self._proxy = Proxy.for_endpoint(self._url)
        #: the URL as logged: no userinfo, secret query values masked
        self.endpoint = self._url.display
        self._context: ssl.SSLContext | None = None
        if self._url.scheme == "https":
            try:
                self._context = ssl.create_default_context(cafile=ca_file or None)
            except (OSError, ssl.SSLError) as exc:
                raise ConfigError(f"ca_file {ca_file}: cannot load CA certificates: "
                                  f"{getattr(exc, 'strerror', None) or exc}") from None
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
        self.pool = ConnectionPool()
        if self._proxy is not None:
            log.info("%s: through proxy %s%s", self.endpoint, self._proxy.display,
                     " (with credentials)" if self._proxy.authorization else "")

    def __repr__(self) -> str:
        return f"ChatClient({self.endpoint!r}, key={'set' if self.__api_key else 'none'})"

    def close(self) -> None:
        """Close the kept-alive connections (a later call opens new ones)."""
        self.pool.close()

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
            reply = dataclasses.replace(reply, attempts=attempt + 1)
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
    def _open(self, fresh: bool = False) -> tuple[http.client.HTTPConnection, bool]:
        """A kept-alive idle connection (unless ``fresh``), or a new one; and whether it was
        kept."""
        idle = None if fresh else self.pool.take()
        if idle is not None:
            return idle, True
        self.pool.opened_one()
        return make_connection(self._url, self._proxy, self.timeout_s, self._context), False

    def _attempt(self, data: bytes, handle: CallHandle) -> tuple[ChatReply, float | None]:
        target, proxy_headers = request_target(self._url, self._proxy)
        headers = {"Content-Type": "application/json", "Accept": "application/json",
                   "User-Agent": "vlm_vpr_ros", **self._url.auth(self.__api_key),
                   **proxy_headers}
        fired = threading.Event()
        current: list[http.client.HTTPConnection] = []

        def _expire() -> None:
            fired.set()
            for c in current:
                _shutdown(c)

        deadline = time.monotonic() + self.timeout_s
        watchdog = threading.Timer(self.timeout_s, _expire)  # one deadline for the attempt
        watchdog.daemon = True
        watchdog.start()
        conn: http.client.HTTPConnection | None = None
        reusable = False
        try:
            for again in (False, True):  # again: only after a kept connection proved stale
                conn, reused = self._open(fresh=again)
                current[:] = [conn]
                handle._attach(conn)
                if fired.is_set():
                    raise TimeoutError("deadline passed")
                try:
                    if conn.sock is None:
                        # the watchdog cannot shut a socket that does not exist yet (a slow
                        # DNS answer, addresses tried in turn): connect within what is left,
                        # and give up if the deadline passed meanwhile
                        conn.timeout = max(0.001, deadline - time.monotonic())
                        conn.connect()
                        if fired.is_set():
                            raise TimeoutError("deadline passed while connecting")
                    if handle.aborted.is_set():  # aborted before the socket existed
                        return ChatReply(None, "cancelled"), None
                    conn.request("POST", target, body=data, headers=headers)
                    resp = conn.getresponse()
                except (http.client.RemoteDisconnected, BrokenPipeError,
                        ConnectionResetError) as exc:
                    if not reused or fired.is_set() or handle.aborted.is_set():
                        raise
                    log.debug("%s: kept-alive connection was closed (%s): reconnecting",
                              self.endpoint, type(exc).__name__)
                    conn.close()
                    continue
                break
            status = resp.status
            retry_after = parse_retry_after(resp.getheader("Retry-After"))
            content_type = resp.getheader("Content-Type") or ""
            declared = resp.length  # Content-Length (None: chunked or until close)
            payload = resp.read(MAX_RESPONSE_BYTES + 1)
            missing = resp.length if declared is not None else None
            reusable = resp.isclosed() and not resp.will_close
        except (OSError, http.client.HTTPException) as exc:
            return self._failure(exc, handle, fired), None
        finally:
            watchdog.cancel()
            handle._attach(None)
            if conn is not None:
                if reusable and not fired.is_set() and not handle.aborted.is_set():
                    self.pool.give_back(conn)
                else:
                    conn.close()
        if handle.aborted.is_set():  # the socket was shut down under a read: data is partial
            return ChatReply(None, "cancelled"), None
        if fired.is_set():
            return ChatReply(None, "timeout"), None
        if missing and len(payload) <= MAX_RESPONSE_BYTES:  # closed before Content-Length
            detail = (f"{self.endpoint}: the answer was cut off after {len(payload)} of "
                      f"{declared} bytes (connection closed)")
            log.info("%s", detail)
            return ChatReply(None, "connection_error", status, detail=detail), None
        if status != 200:
            if status in (401, 403):  # bodies may echo a masked key: do not log them
                log.error("%s: HTTP %d (check the API key / permissions; sent in the %s "
                          "header)", self.endpoint, status, self._url.auth_header)
            elif status == 407:
                log.error("%s: HTTP 407 from the proxy (check the credentials in the proxy "
                          "URL)", self.endpoint)
            else:
                log.debug("%s: HTTP %d: %s", self.endpoint, status, redact(payload[:300]))
            return ChatReply(None, f"http_{status}", status, error_body=payload), retry_after
        return _read_completion(payload, content_type, self.endpoint), None

    def _failure(self, exc: BaseException, handle: CallHandle, fired: threading.Event
                 ) -> ChatReply:
        """The reason of a failed attempt (and one log line where the user must act)."""
        if handle.aborted.is_set():
            return ChatReply(None, "cancelled")
        if fired.is_set() or isinstance(exc, (TimeoutError, socket.timeout)):
            return ChatReply(None, "timeout")
        if isinstance(exc, ssl.SSLCertVerificationError):
            log.error("%s: TLS certificate problem: %s (a private CA: prior option ca_file)",
                      self.endpoint, exc.verify_message or exc.reason)
            return ChatReply(None, "tls_error")
        if isinstance(exc, ssl.SSLError) and not isinstance(
                exc, (ssl.SSLEOFError, ssl.SSLZeroReturnError)):
            plain = exc.reason in ("WRONG_VERSION_NUMBER", "RECORD_LAYER_FAILURE",
                                   "PACKET_LENGTH_TOO_LONG", "HTTP_REQUEST")
            log.error("%s: TLS handshake failed (%s)%s", self.endpoint, exc.reason or exc,
                      ": the server speaks plain http here? use an http:// base_url"
                      if plain else "")
            return ChatReply(None, "tls_error")
        text = str(exc)
        if isinstance(exc, http.client.LineTooLong) or (
                isinstance(exc, http.client.HTTPException) and text.startswith("got more than")):
            detail = (f"{self.endpoint}: the endpoint did not answer as an OpenAI API (its "
                      f"HTTP header is malformed: {redact(text)[:80]}); check base_url")
            log.error("%s", detail)
            return ChatReply(None, "bad_response", detail=detail)
        if self._proxy is not None and text.startswith("Tunnel connection failed"):
            if " 407 " in f"{text} ":
                log.error("%s: the proxy %s refused the credentials (HTTP 407): check the "
                          "user and password in https_proxy", self.endpoint,
                          self._proxy.display)
                return ChatReply(None, "proxy_auth", 407)
            log.warning("%s: proxy %s: %s", self.endpoint, self._proxy.display, redact(text))
        log.debug("%s: %s: %s", self.endpoint, type(exc).__name__, redact(text))
        return ChatReply(None, "connection_error")


def _not_api(endpoint: str, content_type: str, what: str) -> ChatReply:
    ctype = redact(content_type.split(";")[0].strip()[:60]) or "none given"
    return ChatReply(None, "bad_response", 200,
                     detail=f"{endpoint}: the endpoint did not answer as an OpenAI API "
                            f"(content-type {ctype}; {what}): check base_url (a proxy or a "
                            "login page may have answered)")


def _read_completion(payload: bytes, content_type: str = "application/json",
                     endpoint: str = "the endpoint") -> ChatReply:
    """The assistant text of a chat-completions body, or ``bad_response`` /
    ``reasoning_only`` with a :attr:`ChatReply.detail` saying what was wrong."""
    if len(payload) > MAX_RESPONSE_BYTES:
        return ChatReply(None, "bad_response", 200,
                         detail=f"{endpoint}: the answer is larger than "
                                f"{MAX_RESPONSE_BYTES // 2**20} MB")
    try:
        body = json.loads(payload.decode("utf-8"))
    except (ValueError, RecursionError):
        return _not_api(endpoint, content_type, "the body is not JSON")
    try:
        message = body["choices"][0]["message"]
    except (KeyError, IndexError, TypeError):
        return _not_api(endpoint, content_type, "no choices[0].message in the body")
    if not isinstance(message, dict):
        return ChatReply(None, "bad_response", 200)
    finish = body["choices"][0].get("finish_reason")
    finish = finish if isinstance(finish, str) else None
    refusal = message.get("refusal")
    content = message.get("content")
    if isinstance(content, list):  # content parts
        content = "".join(p.get("text", "") for p in content
                          if isinstance(p, dict) and isinstance(p.get("text"), str))
    if isinstance(refusal, str) and refusal and not content:
        return ChatReply(refusal, "refusal", 200, refusal=refusal, finish_reason=finish)
    thought = next((message.get(k) for k in ("reasoning_content", "reasoning")
                    if isinstance(message.get(k), str) and message.get(k).strip()), None)
    if not content and thought is not None and finish != "length":
        return ChatReply(None, "reasoning_only", 200, finish_reason=finish,
                         detail=f"{endpoint}: the answer has no content, only the model's "
                                "reasoning (content null): not read as an answer; the "
                                "server's reasoning parser may be swallowing the reply, or "
                                "raise max_tokens")
    if content is None and finish == "length":  # all tokens spent (on hidden reasoning)
        content = ""
    if not isinstance(content, str):
        return ChatReply(None, "bad_response", 200)
    return ChatReply(content, "", 200, finish_reason=finish)
