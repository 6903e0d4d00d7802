"""On-disk cache of raw VLM answers, so re-running an evaluation never pays twice.

The key is the SHA-256 of the image bytes sent, the endpoint (the chat-completions URL with
its Azure deployment and ``api-version``, redacted: never userinfo or a key), the model name,
the prompt id (name and version) and the answer format (text, or the structured-output schema)
— never a credential. Two endpoints serving the same model name therefore never share answers.
Entries of an older key format are never read (they stay on disk, harmlessly unused).

One small JSON file per entry, written atomically (temporary file + ``os.replace``);
unreadable entries are treated as misses. The raw text is stored (redacted), not the parsed
position, so a better parser applies to old answers too.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

from vlm_vpr_ros.errors import OutputError, PriorError
from vlm_vpr_ros.files.atomic import atomic_write_json
from vlm_vpr_ros.redact import redact

log = logging.getLogger(__name__)

CACHE_FORMAT = 2  # 2: the endpoint and the answer format are part of the key


def image_digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def cache_key(image_sha256: str, model: str, prompt_id: str, endpoint: str = "",
              answer_format: str = "text") -> str:
    """Hex key of one (image, endpoint, model, prompt, answer format) combination; the
    ``endpoint`` must be the redacted URL (no credentials)."""
    blob = json.dumps([CACHE_FORMAT, image_sha256, endpoint, model, prompt_id,
                       answer_format]).encode("utf-8")
    return hashlib.sha256(blob).hexdigest()


class AnswerCache:
    """A folder of ``<key[:2]>/<key>.json`` answer files."""

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = Path(directory).expanduser()
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise PriorError(f"cannot create answer cache folder {self.directory}: {exc}") from exc

    def _path(self, key: str) -> Path:
        return self.directory / key[:2] / f"{key}.json"

    def get(self, key: str) -> dict[str, Any] | None:
        """The stored entry (``raw_text``, ``model``, ``prompt``, ...) or None."""
        path = self._path(key)
        try:
            entry = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as exc:
            log.warning("ignoring unreadable cache entry %s: %s", path, exc)
            return None
        if not isinstance(entry, dict) or not isinstance(entry.get("raw_text"), str):
            log.warning("ignoring malformed cache entry %s", path)
            return None
        return entry

    def put(self, key: str, raw_text: str, **meta: Any) -> None:
        """Store an answer atomically; a write failure is logged, never raised. Every text
        passes the redaction point first (an endpoint may echo request headers)."""
        path = self._path(key)
        entry = {"format": CACHE_FORMAT, "raw_text": redact(raw_text), "created": time.time(),
                 **{k: redact(v) if isinstance(v, str) else v for k, v in meta.items()}}
        try:
            atomic_write_json(path, entry, indent=1, ensure_ascii=False)
        except OutputError as exc:
            log.warning("could not write cache entry %s: %s", path, exc)

    def __len__(self) -> int:
        return sum(1 for _ in self.directory.glob("??/*.json"))
