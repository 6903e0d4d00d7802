"""The one redaction point for secrets in logs, errors and printed messages.

:func:`redact` masks, in any text:

* the userinfo of URLs (``http://user:KEY@host`` -> ``http://***@host``),
* ``Authorization`` / ``api-key`` / ``x-api-key`` header values and ``Bearer`` tokens,
* ``key=value`` / ``"key": "value"`` pairs whose name says secret (api_key, token, password...),
* values shaped like provider keys (``sk-...``, ``AIza...``, ``ghp_...``, ``hf_...``),
* every secret registered with :func:`register_secret` (the API key actually read), line by
  line, so a key with a newline is masked inside tracebacks too.

:class:`RedactingFormatter` applies it to whole log records (message, arguments and traceback);
the CLI and the node install it on their handlers, and error messages printed by the CLI go
through it as well.
"""

from __future__ import annotations

import logging
import re
import threading
from typing import Any

MASK = "***"
_lock = threading.Lock()
_secrets: set[str] = set()

_URL_USERINFO = re.compile(r"(?i)\b([a-z][a-z0-9+.-]*://)[^/@\s'\"]+@")
_HEADER = re.compile(r"(?i)\b(authorization|proxy-authorization|x-api-key|api-key)"
                     r"(['\"]?\s*[:=]\s*['\"]?)(?:bearer\s+|basic\s+)?[^\s'\",}]+")
_BEARER = re.compile(r"(?i)\b(bearer\s+)[A-Za-z0-9._~+/=-]{6,}")
# a ``name: value`` pair whose name ends in a secret word (``client_secret``, ``secret_key``;
# not ``token_param`` or ``max_tokens``); not a ``$NAME`` / ``${NAME}`` reference to a
# variable, whose ":" starts ordinary prose ("no key in $OPENAI_API_KEY: sending ...")
_NAMED = re.compile(r"(?i)(?<![$\w])(?<!\$\{)"
                    r"([a-z_]*(?:api_?key|secret|token|password|passwd)(?:_?key)?)(?![a-z_])"
                    r"(['\"]?\s*[:=]\s*['\"]?)(?!\$|\{)([^\s'\",}&]+)")
_SHAPED = re.compile(r"\b(?:sk-[A-Za-z0-9_-]{8,}|AIza[0-9A-Za-z_-]{20,}|gh[pousr]_[A-Za-z0-9]{20,}"
                     r"|hf_[A-Za-z0-9]{20,}|xox[abpr]-[A-Za-z0-9-]{10,})")
#: a value named like an environment variable (what api_key_env expects)
ENV_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def register_secret(value: str | None) -> None:
    """Mask ``value`` (and each of its lines of 4+ characters) in every later redaction."""
    if not value:
        return
    with _lock:
        for part in [value, *value.splitlines()]:
            part = part.strip()
            if len(part) >= 4:
                _secrets.add(part)


def looks_like_secret(value: str) -> bool:
    """Whether ``value`` is shaped like a key rather than a name (for option checks)."""
    if _SHAPED.search(value):
        return True
    v = value.strip()
    return (len(v) >= 20 and not ENV_NAME.match(v)) or (
        len(v) >= 24 and any(c.isdigit() for c in v) and any(c.islower() for c in v))


def redact(text: object) -> str:
    """``text`` with every secret masked (see the module docstring)."""
    s = text if isinstance(text, str) else str(text)
    with _lock:
        known = sorted(_secrets, key=len, reverse=True)
    for secret in known:
        if secret in s:
            s = s.replace(secret, MASK)
    s = _URL_USERINFO.sub(rf"\1{MASK}@", s)
    s = _HEADER.sub(rf"\1\2{MASK}", s)
    s = _BEARER.sub(rf"\1{MASK}", s)
    s = _NAMED.sub(lambda m: m.group(0) if m.group(1).lower().endswith("_env")
                   else f"{m.group(1)}{m.group(2)}{MASK}", s)
    return _SHAPED.sub(MASK, s)


def redact_obj(obj: Any) -> Any:
    """A copy of a JSON-like value with every string (keys included) passed through
    :func:`redact`: for printing structures as JSON, where escaping would hide a secret from a
    redaction of the dumped text."""
    if isinstance(obj, str):
        return redact(obj)
    if isinstance(obj, dict):
        return {redact_obj(k): redact_obj(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [redact_obj(v) for v in obj]
    return obj


class RedactingFormatter(logging.Formatter):
    """A Formatter whose whole output (message, args, traceback) goes through :func:`redact`."""

    def format(self, record: logging.LogRecord) -> str:
        return redact(super().format(record))


def install(handler: logging.Handler, fmt: str | None = None) -> None:
    """Give ``handler`` a redacting formatter (keeping its format string)."""
    old = handler.formatter
    handler.setFormatter(RedactingFormatter(fmt or (old._fmt if old else None)))
