"""Where a chat request goes and over which connection: the endpoint URL (query string kept),
the auth header, an http proxy with credentials, and the kept-alive connections.

Stdlib ``http.client`` on purpose (see :mod:`vlm_vpr_ros.priors.openai_client`): the caller
needs the socket itself, to shut it down from a watchdog or from another thread.

* :class:`Endpoint` parses ``base_url`` once: ``.../v1`` gets ``/chat/completions`` appended,
  a URL that already ends in ``/chat/completions`` is used as is, and the query string
  (``?api-version=...`` of Azure deployments) is kept. Userinfo and secret-looking query values
  are registered for redaction; :attr:`Endpoint.display` is the redacted URL used in logs and
  in cache keys.
* :class:`Proxy` reads ``https_proxy`` / ``http_proxy`` / ``no_proxy`` once (never for loopback
  hosts); ``http://user:pass@host:port`` sends ``Proxy-Authorization: Basic ...`` on the
  CONNECT of https endpoints and on each request to http endpoints. The credentials are
  registered for redaction.
* :class:`ConnectionPool` keeps idle connections for reuse (one per endpoint when requests are
  sequential; at most one per concurrent request). An idle connection the server has closed
  meanwhile is detected before reuse and replaced.
"""

from __future__ import annotations

import base64
import http.client
import logging
import select
import ssl
import threading
import urllib.parse
import urllib.request
from dataclasses import dataclass

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.redact import redact, register_secret, secret_query_name

log = logging.getLogger(__name__)

_LOOPBACK = ("127.", "localhost", "::1", "[::1]")
AUTH_HEADERS = ("auto", "bearer", "api-key", "none")
_AZURE_HOST = (".openai.azure.com", ".cognitiveservices.azure.com", ".services.ai.azure.com")
_COMPLETIONS = "/chat/completions"


def _split(url: str, what: str) -> urllib.parse.SplitResult:
    try:
        parts = urllib.parse.urlsplit(str(url).strip())
        parts.port  # noqa: B018 - raises ValueError on a bad port
    except ValueError:
        parts = None
    if parts is None or parts.scheme not in ("http", "https") or not parts.hostname:
        raise ConfigError(f"{what} must be an http(s) URL, got {redact(url)!r}")
    return parts


def _host_port(parts: urllib.parse.SplitResult) -> str:
    host = parts.hostname or ""
    host = f"[{host}]" if ":" in host else host
    return f"{host}{f':{parts.port}' if parts.port else ''}"


@dataclass(frozen=True)
class Endpoint:
    """The chat-completions URL of ``base_url`` and how to authenticate to it."""

    scheme: str
    host: str
    port: int | None
    target: str  # path + "?query" sent in the request line
    display: str  # scheme://host[:port]/path[?query], redacted: for logs and cache keys
    auth_header: str  # "bearer", "api-key" or "none"

    @classmethod
    def parse(cls, base_url: str, auth_header: str = "auto") -> "Endpoint":
        parts = _split(base_url, "base_url")
        register_secret(urllib.parse.unquote(parts.password or ""))  # never log URL userinfo
        register_secret(urllib.parse.unquote(parts.username or ""))
        for pair in parts.query.split("&"):
            name, _, value = pair.partition("=")
            if secret_query_name(urllib.parse.unquote_plus(name)):
                register_secret(value)  # as sent (percent-encoded) and as decoded
                register_secret(urllib.parse.unquote_plus(value))
        path = parts.path.rstrip("/")
        if not path.endswith(_COMPLETIONS):
            path += _COMPLETIONS
        target = f"{path}?{parts.query}" if parts.query else path
        if auth_header not in AUTH_HEADERS:
            raise ConfigError(f"unknown auth_header {auth_header!r}; choices: "
                              f"{', '.join(AUTH_HEADERS)}")
        if auth_header == "auto":
            azure = ((parts.hostname or "").lower().endswith(_AZURE_HOST)
                     or "/openai/deployments/" in path)
            auth_header = "api-key" if azure else "bearer"
        display = redact(f"{parts.scheme}://{_host_port(parts)}{target}")
        return cls(parts.scheme, parts.hostname or "", parts.port, target, display, auth_header)

    @property
    def origin(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}{f':{self.port}' if self.port else ''}"

    def auth(self, key: str | None) -> dict[str, str]:
        """The header carrying ``key`` (none without a key)."""
        if not key or self.auth_header == "none":
            return {}
        if self.auth_header == "api-key":
            return {"api-key": key}
        return {"Authorization": f"Bearer {key}"}


@dataclass(frozen=True)
class Proxy:
    """An http proxy (``http://[user:pass@]host:port``) from the environment."""

    host: str
    port: int
    authorization: str | None  # "Basic ..." or None
    display: str  # http://host:port (no credentials)

    @classmethod
    def for_endpoint(cls, endpoint: Endpoint) -> "Proxy | None":
        """The proxy the environment names for ``endpoint`` (None: direct)."""
        host = endpoint.host
        if host.startswith(_LOOPBACK) or urllib.request.proxy_bypass(host):
            return None
        url = urllib.request.getproxies().get(endpoint.scheme)
        if not url:
            return None
        if "://" not in url:
            url = f"http://{url}"
        what = f"{endpoint.scheme}_proxy"
        parts = _split(url, what)
        user = urllib.parse.unquote(parts.username or "")
        password = urllib.parse.unquote(parts.password or "")
        register_secret(password)
        register_secret(user)
        if parts.scheme != "http":
            raise ConfigError(f"{what} is an {parts.scheme}:// proxy URL; only http:// proxies "
                              "are supported (the tunnel to the endpoint is TLS already)")
        auth = None
        if parts.username is not None:
            token = base64.b64encode(f"{user}:{password}".encode("utf-8")).decode("ascii")
            register_secret(token)
            auth = f"Basic {token}"
        host = parts.hostname or ""
        port = parts.port or 3128
        return cls(host, port, auth, f"http://{f'[{host}]' if ':' in host else host}:{port}")


def request_target(endpoint: Endpoint, proxy: Proxy | None) -> tuple[str, dict[str, str]]:
    """The request-line target and the per-request proxy headers: origin-form, or the
    absolute form (with ``Proxy-Authorization``) for an http endpoint behind a proxy."""
    if endpoint.scheme == "http" and proxy is not None:
        headers = {"Proxy-Authorization": proxy.authorization} if proxy.authorization else {}
        return endpoint.origin + endpoint.target, headers
    return endpoint.target, {}


def make_connection(endpoint: Endpoint, proxy: Proxy | None, timeout_s: float,
                    context: ssl.SSLContext | None) -> http.client.HTTPConnection:
    """A new, not yet connected connection (https through a proxy: a CONNECT tunnel that
    carries the proxy credentials)."""
    if endpoint.scheme == "https":
        if proxy is not None:
            conn = http.client.HTTPSConnection(proxy.host, proxy.port, timeout=timeout_s,
                                               context=context)
            tunnel = {"Proxy-Authorization": proxy.authorization} if proxy.authorization else {}
            conn.set_tunnel(endpoint.host, endpoint.port or 443, headers=tunnel)
            return conn
        return http.client.HTTPSConnection(endpoint.host, endpoint.port, timeout=timeout_s,
                                           context=context)
    if proxy is not None:
        return http.client.HTTPConnection(proxy.host, proxy.port, timeout=timeout_s)
    return http.client.HTTPConnection(endpoint.host, endpoint.port, timeout=timeout_s)


def _dropped(conn: http.client.HTTPConnection) -> bool:
    """Whether an idle connection is unusable: closed, or readable (EOF or stray bytes)."""
    sock = conn.sock
    if sock is None:
        return True
    try:
        return bool(select.select([sock], [], [], 0)[0])
    except (OSError, ValueError):
        return True


class ConnectionPool:
    """Idle kept-alive connections of one endpoint, most recently used first."""

    def __init__(self, max_idle: int = 8) -> None:
        self.max_idle = max_idle
        self._idle: list[http.client.HTTPConnection] = []
        self._lock = threading.Lock()
        self.opened = 0  # connections created (for diagnostics and tests)

    def take(self) -> http.client.HTTPConnection | None:
        """A live idle connection, or None (the caller opens a new one and calls opened_one)."""
        while True:
            with self._lock:
                if not self._idle:
                    return None
                conn = self._idle.pop()
            if not _dropped(conn):
                return conn
            conn.close()

    def opened_one(self) -> None:
        with self._lock:
            self.opened += 1

    def give_back(self, conn: http.client.HTTPConnection) -> None:
        with self._lock:
            if len(self._idle) < self.max_idle:
                self._idle.append(conn)
                return
        conn.close()

    def close(self) -> None:
        with self._lock:
            idle, self._idle = self._idle, []
        for conn in idle:
            conn.close()
