"""TEST FIXTURE: an authenticating http proxy on 127.0.0.1 and a throw-away TLS certificate.

:class:`ConnectProxy` does what a corporate proxy does: ``CONNECT host:port`` (https) and
absolute-form requests (http) are accepted only with ``Proxy-Authorization: Basic`` of its user
and password (else ``407 Proxy Authentication Required``), and every accepted connection is
relayed to ``upstream`` whatever host was named (so a test can use a name such as
``vlm.test`` that no resolver knows). It records what it saw::

    with ChatServer(tls=cert) as srv, ConnectProxy(srv.port, "robot", "pw") as proxy:
        monkeypatch.setenv("https_proxy", proxy.url)
        ...
        proxy.connects  # ["vlm.test:<port>", ...]; proxy.refused: 407s sent

:func:`self_signed` makes a certificate for a host name with the ``openssl`` command (None
when it is missing: the tests that need one skip).
"""

from __future__ import annotations

import base64
import select
import shutil
import socket
import subprocess
import threading
from pathlib import Path


def self_signed(folder: Path, host: str = "vlm.test") -> tuple[str, str] | None:
    """(cert.pem, key.pem) of a one-day self-signed certificate for ``host``."""
    exe = shutil.which("openssl")
    if exe is None:
        return None
    cert, key = folder / f"{host}.pem", folder / f"{host}.key"
    proc = subprocess.run(
        [exe, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
         "-nodes", "-days", "1", "-subj", f"/CN={host}", "-addext",
         f"subjectAltName=DNS:{host}", "-keyout", str(key), "-out", str(cert)],
        capture_output=True, timeout=60)
    return (str(cert), str(key)) if proc.returncode == 0 else None


class ConnectProxy:
    """Authenticating CONNECT / absolute-form proxy relaying to 127.0.0.1:``upstream``."""

    def __init__(self, upstream: int, user: str | None = None,
                 password: str | None = None) -> None:
        self.upstream = upstream
        self.user, self.password = user, password
        self.connects: list[str] = []  # CONNECT targets accepted
        self.forwards: list[str] = []  # absolute-form request lines accepted
        self.refused = 0  # 407 answers
        self.connections = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self._threads: list[threading.Thread] = []

    @property
    def port(self) -> int:
        assert self._sock is not None
        return int(self._sock.getsockname()[1])

    @property
    def url(self) -> str:
        cred = f"{self.user}:{self.password}@" if self.user is not None else ""
        return f"http://{cred}127.0.0.1:{self.port}"

    def start(self) -> "ConnectProxy":
        self._sock = socket.create_server(("127.0.0.1", 0))
        self._sock.settimeout(0.1)
        t = threading.Thread(target=self._serve, name="proxy-fixture", daemon=True)
        t.start()
        self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in list(self._threads):
            t.join(timeout=5)
        if self._sock is not None:
            self._sock.close()

    def __enter__(self) -> "ConnectProxy":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- serving -----------------------------------------------------------------------------
    def _serve(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            with self._lock:
                self.connections += 1
            t = threading.Thread(target=self._client, args=(conn,), daemon=True)
            t.start()
            self._threads.append(t)

    def _authorized(self, head: bytes) -> bool:
        if self.user is None:
            return True
        token = base64.b64encode(f"{self.user}:{self.password}".encode()).decode()
        for line in head.split(b"\r\n")[1:]:
            name, _, value = line.decode("latin-1").partition(":")
            if name.strip().lower() == "proxy-authorization":
                return value.strip() == f"Basic {token}"
        return False

    def _client(self, conn: socket.socket) -> None:
        with conn:
            conn.settimeout(10.0)
            head = b""
            try:
                while b"\r\n\r\n" not in head and len(head) < 65536:
                    chunk = conn.recv(4096)
                    if not chunk:
                        return
                    head += chunk
            except OSError:
                return
            line = head.split(b"\r\n", 1)[0].decode("latin-1")
            method, _, rest = line.partition(" ")
            if not self._authorized(head):
                with self._lock:
                    self.refused += 1
                conn.sendall(b"HTTP/1.1 407 Proxy Authentication Required\r\n"
                             b"Proxy-Authenticate: Basic realm=\"fixture\"\r\n"
                             b"Content-Length: 0\r\nConnection: close\r\n\r\n")
                return
            try:
                up = socket.create_connection(("127.0.0.1", self.upstream), timeout=10.0)
            except OSError:
                conn.sendall(b"HTTP/1.1 502 Bad Gateway\r\nContent-Length: 0\r\n\r\n")
                return
            with up:
                if method == "CONNECT":
                    with self._lock:
                        self.connects.append(rest.split(" ")[0])
                    tail = head.split(b"\r\n\r\n", 1)[1]
                    conn.sendall(b"HTTP/1.1 200 Connection established\r\n\r\n")
                else:  # absolute-form: the upstream fixture accepts the absolute target
                    with self._lock:
                        self.forwards.append(line)
                    tail = head
                if tail:
                    up.sendall(tail)
                self._relay(conn, up)

    def _relay(self, a: socket.socket, b: socket.socket) -> None:
        peers = {a: b, b: a}
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select(list(peers), [], [], 0.1)
                for s in ready:
                    data = s.recv(65536)
                    if not data:
                        return
                    peers[s].sendall(data)
            except OSError:
                return
