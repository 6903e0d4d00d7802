"""On-disk cache of raw VLM answers, so re-running an evaluation never pays twice.

The key is the SHA-256 of the image bytes sent, the model name and the prompt id (name and
version) — never the endpoint's credentials. One small JSON file per entry, written atomically
(temporary file + ``os.replace``); unreadable entries are treated as misses. The raw text is
stored, not the parsed position, so a better parser applies to old answers too.
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

log = logging.getLogger(__name__)

CACHE_FORMAT = 1


def image_digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def cache_key(image_sha256: str, model: str, prompt_id: str) -> str:
    """Hex key of one (image, model, prompt) combination."""
    blob = json.dumps([CACHE_FORMAT, image_sha256, model, prompt_id]).encode("utf-8")
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
        """Store an answer atomically; a write failure is logged, never raised."""
        path = self._path(key)
        entry = {"format": CACHE_FORMAT, "raw_text": raw_text, "created": time.time(), **meta}
        try:
            atomic_write_json(path, entry, indent=1, ensure_ascii=False)
        except OutputError as exc:
            log.warning("could not write cache entry %s: %s", path, exc)

    def __len__(self) -> int:
        return sum(1 for _ in self.directory.glob("??/*.json"))
