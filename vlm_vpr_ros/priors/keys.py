"""API keys of VLM endpoints: read once at start, checked, registered for redaction.

A key comes from ``api_key_file`` or from the environment variable named by ``api_key_env``.
It is registered with :func:`vlm_vpr_ros.redact.register_secret` before anything else happens,
so no later message can show it. A key must be printable ASCII: a copy-paste that brought a
typographic quote (’), an ellipsis (…), a non-breaking space or a line break would otherwise
fail on every request (HTTP headers are ASCII), so it is refused at start with one line.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from vlm_vpr_ros.errors import ConfigError, PriorError
from vlm_vpr_ros.redact import ENV_NAME, looks_like_secret, register_secret

log = logging.getLogger(__name__)

__all__ = ["check_key", "read_api_key"]


def read_api_key(env: str | None, path: str | None) -> str | None:
    """The API key from ``path`` or ``$env`` (None when unset); ConfigError/PriorError with one
    line when it cannot be used. The key is never part of a message."""
    if path:
        try:
            key = Path(path).expanduser().read_text(encoding="utf-8", errors="replace").strip()
        except OSError as exc:
            raise PriorError(f"cannot read api_key_file {path}: {exc.strerror}") from None
        if not key:
            raise PriorError(f"api_key_file {path} is empty")
        register_secret(key)
        return check_key(key, f"api_key_file {path}")
    if env and (looks_like_secret(str(env)) or not ENV_NAME.match(str(env))):
        register_secret(str(env))
        raise ConfigError("api_key_env must be the NAME of an environment variable holding the "
                          "key (e.g. OPENAI_API_KEY), not the key itself; the value given was "
                          "not logged")
    key = os.environ.get(env or "", "").strip() if env else ""
    register_secret(key)
    if key:
        return check_key(key, f"${env}")
    log.info("no API key in $%s: sending requests without one (fine for local servers such "
             "as Ollama or vLLM without --api-key)", env)
    return None


def check_key(key: str, where: str) -> str:
    """``key`` when it is printable ASCII; else a one-line ConfigError naming ``where``."""
    for c in key:
        if " " < c <= "~":
            continue
        if c in "\r\n" or ord(c) < 32 or ord(c) == 127:
            what = "a line break or control character"
        elif c.isspace():
            what = f"a space character (U+{ord(c):04X})"
        else:
            what = f"the non-ASCII character U+{ord(c):04X}"
        raise ConfigError(f"the API key in {where} contains {what} (copy-paste error?); keys "
                          "must be printable ASCII; the key was not logged")
    return key
