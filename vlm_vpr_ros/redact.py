"""The one redaction point for secrets in logs, errors and printed messages.

:func:`redact` masks, in any text:

* the userinfo of URLs (``http://user:KEY@host`` -> ``http://***@host``),
* ``Authorization`` / ``api-key`` / ``x-api-key`` header values and ``Bearer`` tokens,
* ``key=value`` / ``"key": "value"`` pairs whose name says secret (api_key, token, password...),
* values shaped like provider keys (``sk-...``, ``AIza...``, ``ghp_...``, ``hf_...``),
* the value of every URL query parameter whose name says secret (``?subscription-key=``,
  ``&api-key=``, ``key``, ``token``, ``sig``, ``code``, ``password``, ``auth``...: the rule
  :func:`secret_query_name` that the VLM client also uses for its base URL),
* every secret registered with :func:`register_secret` (the API key actually read), line by
  line, so a key with a newline is masked inside tracebacks too; an echo of it is masked in
  every encoding this module can recognise: any letter case, percent-encoded, hex, base64
  (standard and URL-safe, at any alignment inside a longer base64 text), and, for secrets of
  16+ characters, any piece of 8+ characters of it (a key split in two by an echo).

:class:`RedactingFormatter` applies it to whole log records (message, arguments and traceback);
the CLI and the node install it on their handlers, and error messages printed by the CLI go
through it as well.
"""

from __future__ import annotations

import base64
import logging
import re
import threading
import urllib.parse
from typing import Any

MASK = "***"
_lock = threading.Lock()
_secrets: set[str] = set()
_patterns: dict[str, re.Pattern[str]] = {}  # secret -> its echoes in every known encoding
_pieces: dict[str, str] = {}  # lower-cased 8-character piece -> the secret it is from
PIECE = 8  # a secret of 16+ characters: any 8 of them in a row are masked

_URL_USERINFO = re.compile(r"(?i)\b([a-z][a-z0-9+.-]*://)[^/@\s'\"]+@")
_HEADER = re.compile(r"(?i)\b(authorization|proxy-authorization|x-api-key|api-key)"
                     r"(['\"]?\s*[:=]\s*['\"]?)(?:bearer\s+|basic\s+)?[^\s'\",}&]+")
_BEARER = re.compile(r"(?i)\b(bearer\s+)[A-Za-z0-9._~+/=-]{6,}")
# a ``name: value`` pair whose name ends in a secret word (``client_secret``, ``secret_key``;
# not ``token_param`` or ``max_tokens``); not a ``$NAME`` / ``${NAME}`` reference to a
# variable, whose ":" starts ordinary prose ("no key in $OPENAI_API_KEY: sending ...")
_NAMED = re.compile(r"(?i)(?<![$\w])(?<!\$\{)"
                    r"([a-z_]*(?:api_?key|secret|token|password|passwd)(?:_?key)?)(?![a-z_])"
                    r"(['\"]?\s*[:=]\s*['\"]?)(?!\$|\{)([^\s'\",}&]+)")
_SHAPED = re.compile(r"\b(?:sk-[A-Za-z0-9_-]{8,}|AIza[0-9A-Za-z_-]{20,}|gh[pousr]_[A-Za-z0-9]{20,}"
                     r"|hf_[A-Za-z0-9]{20,}|xox[abpr]-[A-Za-z0-9-]{10,})")
#: query parameter names that say secret (whole name, or its last ``-``/``_`` word)
_SECRET_WORDS = ("key", "apikey", "sig", "signature", "token", "secret", "password", "passwd",
                 "pwd", "code", "auth", "credential", "credentials", "sas", "jwt", "session")
_QUERY = re.compile(r"(?i)([?&;]([A-Za-z0-9_.-]{1,64})=)([^&#\s'\"<>]+)")
_MASKS = re.compile(r"(?:\*\*\*){2,}")  # adjacent masks read as one
#: a value named like an environment variable (what api_key_env expects)
ENV_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def secret_query_name(name: str) -> bool:
    """Whether a URL query parameter named ``name`` carries a secret (``subscription-key``,
    ``api-key``, ``access_token``, ``sig``, ``code``...; not ``api-version``)."""
    n = name.lower()
    words = re.split(r"[-_.]", n)
    return n in _SECRET_WORDS or words[-1] in _SECRET_WORDS or n.endswith(("key", "token"))


def _b64_cores(raw: bytes) -> list[str]:
    """The base64 text of ``raw`` at each of the 3 alignments it can have inside a longer
    encoded text (the characters that do not depend on the bytes around it)."""
    out = []
    for enc in (base64.b64encode, base64.urlsafe_b64encode):
        for shift in range(3):
            text = enc(b"\0" * shift + raw).decode().rstrip("=")
            lead = (shift * 4 + 2) // 3  # characters touched by the padding bytes
            end = ((shift + len(raw)) * 4) // 3  # whole characters of the secret's bytes
            core = text[lead:end]
            if len(core) >= 6:
                out.append(core)
    return out


def _pattern(secret: str) -> re.Pattern[str]:
    raw = secret.encode("utf-8")
    forms = {secret, urllib.parse.quote(secret, safe=""), urllib.parse.quote_plus(secret),
             raw.hex()}
    forms.update(_b64_cores(raw))
    alts = sorted((re.escape(f) for f in forms if f), key=len, reverse=True)
    return re.compile("|".join(alts), re.IGNORECASE)


def register_secret(value: str | None) -> None:
    """Mask ``value`` (and each of its lines of 4+ characters) in every later redaction, in
    every encoding :func:`redact` recognises (module docstring)."""
    if not value:
        return
    with _lock:
        for part in [value, *value.splitlines()]:
            part = part.strip()
            if len(part) >= 4 and part not in _secrets:
                _secrets.add(part)
                _patterns[part] = _pattern(part)
                if len(part) >= 16:
                    low = part.lower()
                    for i in range(len(low) - PIECE + 1):
                        _pieces.setdefault(low[i:i + PIECE], part)


def _mask_pieces(s: str) -> str:
    """Mask every run of 8+ characters of ``s`` that is a piece of a registered secret."""
    if not _pieces or len(s) < PIECE:
        return s
    low, hits, i = s.lower(), [], 0
    while i <= len(low) - PIECE:
        if low[i:i + PIECE] in _pieces:
            j = i + 1
            while j <= len(low) - PIECE and low[j:j + PIECE] in _pieces:
                j += 1
            hits.append((i, j + PIECE - 1))
            i = j + PIECE - 1
        else:
            i += 1
    for a, b in reversed(hits):
        s = s[:a] + MASK + s[b:]
    return s


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
        known = [_patterns[k] for k in sorted(_secrets, key=len, reverse=True)]
    for pattern in known:
        s = pattern.sub(MASK, s)
    s = _URL_USERINFO.sub(rf"\1{MASK}@", s)
    s = _QUERY.sub(lambda m: f"{m.group(1)}{MASK}" if secret_query_name(m.group(2))
                   and m.group(3) != MASK else m.group(0), s)
    s = _HEADER.sub(rf"\1\2{MASK}", s)
    s = _BEARER.sub(rf"\1{MASK}", s)
    s = _NAMED.sub(lambda m: m.group(0) if m.group(1).lower().endswith("_env")
                   else f"{m.group(1)}{m.group(2)}{MASK}", s)
    s = _SHAPED.sub(MASK, s)
    # pieces last: a piece shared with another key (the "sk-proj-" of any OpenAI key) must not
    # cut that key's shape before the rules above have masked it whole
    return _MASKS.sub(MASK, _mask_pieces(s))


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
