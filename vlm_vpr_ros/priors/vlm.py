"""VLM prior providers: ``openai`` (any OpenAI-compatible chat-completions endpoint) and
``answers`` (recorded raw answers of real VLMs, parsed offline with the same parser).

Both return failures as :class:`PriorResult` values with a ``reason`` — ``timeout``,
``http_429``, ``http_500``, ``connection_error``, ``bad_response``, ``refusal``,
``no_coordinates``, ``out_of_range``, ``no_image``, ``bad_image``, ``cancelled`` — never as
exceptions. ``openai``'s :meth:`~OpenAIPrior.request` returns a future at once; the work runs in
a bounded thread pool (``max_concurrency``).
"""

from __future__ import annotations

import base64
import concurrent.futures as cf
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.errors import ConfigError, DataError, ImageDecodeError, PriorError
from vlm_vpr_ros.files.images import check_rgb, decode_image_bytes, encode_jpeg
from vlm_vpr_ros.priors import register_prior_provider
from vlm_vpr_ros.priors.base import Prior, PriorProvider, PriorQuery, PriorResult
from vlm_vpr_ros.priors.cache import AnswerCache, cache_key, image_digest
from vlm_vpr_ros.priors.openai_client import CallHandle, ChatClient
from vlm_vpr_ros.priors.parsing import PARSER_MODES, parse_answer
from vlm_vpr_ros.priors.prompts import build_messages, get_prompt
from vlm_vpr_ros.redact import ENV_NAME, looks_like_secret, register_secret

log = logging.getLogger(__name__)

__all__ = ["AnswersPrior", "OpenAIPrior", "read_answers_csv", "result_from_text"]


def result_from_text(raw: str | None, source: str, parser: str = "robust",
                     latency_s: float = 0.0, extra: dict[str, Any] | None = None
                     ) -> PriorResult:
    """Parse a raw answer into a PriorResult (ok, or a failure with the parser's reason)."""
    parsed = parse_answer(raw, parser)
    extra = {**(extra or {}), "parser": parser}
    if parsed.ok:
        extra.update(parse_method=parsed.method, **parsed.info)
        assert parsed.lat is not None and parsed.lon is not None
        return PriorResult(Prior(parsed.lat, parsed.lon, source), source, "", latency_s, raw,
                           extra)
    return PriorResult(None, source, parsed.reason, latency_s, raw, extra)


def _read_api_key(env: str | None, path: str | None) -> str | None:
    """The API key from ``api_key_file`` or ``$api_key_env``; registered for redaction."""
    if path:
        try:
            key = Path(path).expanduser().read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise PriorError(f"cannot read api_key_file {path}: {exc.strerror}") from None
        if not key:
            raise PriorError(f"api_key_file {path} is empty")
        register_secret(key)
        return _check_key(key, f"api_key_file {path}")
    if env and (looks_like_secret(str(env)) or not ENV_NAME.match(str(env))):
        register_secret(str(env))
        raise ConfigError("api_key_env must be the NAME of an environment variable holding the "
                          "key (e.g. OPENAI_API_KEY), not the key itself; the value given was "
                          "not logged")
    key = os.environ.get(env or "", "").strip() if env else ""
    register_secret(key)
    if key:
        _check_key(key, f"${env}")
    if not key:
        log.info("no API key in $%s: sending requests without Authorization (fine for local "
                 "servers such as Ollama or vLLM)", env)
    return key or None


def _check_key(key: str, where: str) -> str:
    if any(ord(c) < 32 or ord(c) == 127 for c in key):
        raise ConfigError(f"the API key in {where} contains a line break or control character "
                          "(copy-paste error?); the key was not logged")
    return key


def _sniff_mime(data: bytes) -> str | None:
    if data[:3] == b"\xff\xd8\xff":
        return "image/jpeg"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "image/png"
    return None


def prepare_image(query: PriorQuery, max_image_side: int | None) -> tuple[bytes, str] | None:
    """Bytes and MIME type to send: the original file when it fits, else a (downscaled) JPEG
    of the pixels. None when the query carries no image; ImageDecodeError when undecodable."""
    if query.encoded:
        data = bytes(query.encoded)
        mime = _sniff_mime(data)
        if mime and not max_image_side:
            return data, mime
        rgb = decode_image_bytes(data, "prior query image")
        if mime and max(rgb.shape[:2]) <= (max_image_side or 0):
            return data, mime
    elif query.image is not None:
        rgb = check_rgb(query.image, "prior query image")
    else:
        return None
    side = max(rgb.shape[:2])
    if max_image_side and side > max_image_side:
        scale = max_image_side / side
        size = (max(1, round(rgb.shape[1] * scale)), max(1, round(rgb.shape[0] * scale)))
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    return encode_jpeg(np.ascontiguousarray(rgb), quality=90), "image/jpeg"


class OpenAIPrior(PriorProvider):
    """Ask a VLM behind an OpenAI-compatible ``/chat/completions`` endpoint for a coarse
    position, with least-to-most prompting, robust parsing, retries, rate limiting and cache."""

    name = "openai"

    def __init__(self, base_url: str = "https://api.openai.com/v1", model: str = "gpt-4o",
                 api_key_env: str = "OPENAI_API_KEY", api_key_file: str | None = None,
                 timeout_s: float = 60.0, max_retries: int = 3, backoff_s: float = 1.0,
                 max_concurrency: int = 4, min_interval_s: float = 0.0,
                 temperature: float = 0.0, max_image_side: int | None = 1024,
                 parser: str = "robust", cache_dir: str | None = None, prompt: str = "ltm",
                 max_tokens: int = 600) -> None:
        choose(parser, dict.fromkeys(PARSER_MODES), "answer parser")
        self.prompt = get_prompt(prompt)
        try:
            self.max_concurrency = int(max_concurrency)
            self.temperature = float(temperature)
            self.max_tokens = int(max_tokens)
            self.max_image_side = int(max_image_side) if max_image_side else None
            timeout_s, backoff_s = float(timeout_s), float(backoff_s)
            max_retries, min_interval_s = int(max_retries), float(min_interval_s)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"openai prior: invalid number ({exc}); timeout_s, backoff_s, "
                              "min_interval_s, temperature are seconds/floats, max_retries, "
                              "max_concurrency, max_tokens, max_image_side integers") from None
        if self.max_concurrency < 1 or self.max_tokens < 1:
            raise ConfigError("openai prior: max_concurrency and max_tokens must be >= 1")
        if self.max_image_side is not None and self.max_image_side < 32:
            raise ConfigError("openai prior: max_image_side must be >= 32 (or null)")
        self.model = str(model)
        self.parser = parser
        self.source = self.name = f"openai:{self.model}"  # name labels timeouts too
        self.client = ChatClient(base_url, _read_api_key(api_key_env, api_key_file),
                                 timeout_s=float(timeout_s), max_retries=int(max_retries),
                                 backoff_s=float(backoff_s),
                                 min_interval_s=float(min_interval_s))
        self.cache = AnswerCache(cache_dir) if cache_dir else None
        self._pool = cf.ThreadPoolExecutor(self.max_concurrency, thread_name_prefix="vlm-prior")
        self._lock = threading.Lock()
        self._pending: dict[cf.Future, CallHandle] = {}
        self._closed = False

    def __repr__(self) -> str:
        return f"OpenAIPrior({self.client.endpoint!r}, model={self.model!r})"

    # --- async API ---------------------------------------------------------------------------
    def request(self, query: PriorQuery) -> "cf.Future[PriorResult]":
        """Start a request; returns a future at once. ``future.cancel()`` aborts the call."""
        fut: cf.Future[PriorResult] = cf.Future()
        handle = CallHandle()
        with self._lock:
            if self._closed:
                fut.set_result(PriorResult.failure(self.source, "cancelled"))
                return fut
            self._pending[fut] = handle
            self._pool.submit(self._run, query, fut, handle, time.monotonic())
        fut.add_done_callback(self._on_done)
        return fut

    def _on_done(self, fut: cf.Future) -> None:
        with self._lock:
            handle = self._pending.pop(fut, None)
        if handle is not None and fut.cancelled():
            handle.abort()

    def close(self) -> None:
        """Abort all pending requests (their futures resolve with reason ``cancelled``)."""
        with self._lock:
            self._closed = True
            pending = list(self._pending.items())
        for fut, handle in pending:
            handle.abort()
            _resolve(fut, PriorResult.failure(self.source, "cancelled"))
        self._pool.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> "OpenAIPrior":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- work (pool thread) ------------------------------------------------------------------
    def _run(self, query: PriorQuery, fut: cf.Future, handle: CallHandle, t0: float) -> None:
        if fut.done():
            return
        try:
            result = self._work(query, handle, t0)
        except Exception as exc:  # noqa: BLE001 - a bug must reach the caller as a value
            log.exception("VLM prior request failed unexpectedly")
            result = PriorResult.failure(self.source, f"error: {type(exc).__name__}",
                                         time.monotonic() - t0)
        _resolve(fut, result)

    def _work(self, query: PriorQuery, handle: CallHandle, t0: float) -> PriorResult:
        try:
            image = prepare_image(query, self.max_image_side)
        except ImageDecodeError as exc:
            log.warning("prior query image unusable: %s", exc)
            return PriorResult.failure(self.source, "bad_image", time.monotonic() - t0)
        if image is None:
            return PriorResult.failure(self.source, "no_image")
        data, mime = image
        digest = image_digest(data)
        key = cache_key(digest, self.model, self.prompt.id)
        extra: dict[str, Any] = {"model": self.model, "prompt": self.prompt.id,
                                 "image_sha256": digest, "cached": False}
        if self.cache is not None and (entry := self.cache.get(key)) is not None:
            extra["cached"] = True
            return result_from_text(entry["raw_text"], self.source, self.parser,
                                    time.monotonic() - t0, extra)
        url = f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"
        body = {"model": self.model, "messages": build_messages(self.prompt, url),
                "temperature": self.temperature, "max_tokens": self.max_tokens}
        reply = self.client.call(body, handle)
        latency = time.monotonic() - t0
        extra["attempts"] = reply.attempts
        if reply.reason == "refusal" and reply.refusal:
            return PriorResult(None, self.source, "refusal", latency, reply.refusal, extra)
        if not reply.ok or reply.content is None:
            return PriorResult(None, self.source, reply.reason or "bad_response", latency,
                               None, extra)
        if self.cache is not None:
            self.cache.put(key, reply.content, model=self.model, prompt=self.prompt.id,
                           image_sha256=digest)
        return result_from_text(reply.content, self.source, self.parser, latency, extra)


def _resolve(fut: cf.Future, result: PriorResult) -> None:
    if not fut.done():
        try:
            fut.set_result(result)
        except cf.InvalidStateError:
            pass  # cancelled or resolved by close() meanwhile


# --- recorded answers ------------------------------------------------------------------------
def read_answers_csv(path: str | os.PathLike[str]) -> dict[str, str]:
    """{filename: raw response} from a CSV with columns ``filename, response`` (others
    ignored; ``file`` is accepted for ``filename``). A file answered twice with different
    responses is a DataError naming both lines."""
    from vlm_vpr_ros.files.csvio import read_rows, unique_rows

    cols, rows = read_rows(path, "answers CSV")
    fcol = "filename" if "filename" in cols else "file" if "file" in cols else None
    if fcol is None or "response" not in cols:
        raise DataError(f"{path}: needs columns filename,response; has {cols}")
    return unique_rows(((n, row[fcol], row["response"] or "") for n, row in rows
                        if row.get(fcol)), path, "filename")


class AnswersPrior(PriorProvider):
    """Recorded raw VLM answers (``filename, response``), parsed like live ones."""

    name = "answers"

    def __init__(self, path: str, parser: str = "robust") -> None:
        choose(parser, dict.fromkeys(PARSER_MODES), "answer parser")
        self.parser = parser
        self.answers = read_answers_csv(path)
        self._by_base = {os.path.basename(k): v for k, v in self.answers.items()}
        self.source = self.name = f"answers:{Path(path).stem}"

    def _compute(self, query: PriorQuery) -> PriorResult:
        if not query.key:
            return PriorResult.failure(self.source, "no_key")
        raw = self.answers.get(query.key)
        if raw is None:
            raw = self._by_base.get(os.path.basename(query.key))
        if raw is None:
            return PriorResult.failure(self.source, "not_recorded")
        return result_from_text(raw, self.source, self.parser)


register_prior_provider("openai", OpenAIPrior)
register_prior_provider("answers", AnswersPrior)
