"""VLM prior providers: ``openai`` (any OpenAI-compatible chat-completions endpoint) and
``answers`` (recorded raw answers of real VLMs, parsed offline with the same parser).

Both return failures as :class:`PriorResult` values with a ``reason`` — ``timeout``,
``http_429``, ``http_500``, ``connection_error``, ``tls_error``, ``proxy_auth``,
``bad_response``, ``reasoning_only``, ``refusal``, ``truncated``, ``no_coordinates``,
``out_of_range``, ``suspicious_null_island``, ``suspicious_injection``,
``suspicious_ambiguous``, ``no_image``, ``bad_image``, ``cancelled`` — never as exceptions;
``extra["detail"]`` (also logged once as a warning) says in one line what the endpoint did
wrong when the reason alone would not (a non-API answer and its content type, a body cut
off, an answer only in ``reasoning``). An answer cut at the token limit
(``finish_reason: length``) is ``truncated`` even when a position can be read from it: it is
not the model's final answer. ``openai``'s :meth:`~OpenAIPrior.request` returns a future
at once; the work runs in a bounded thread pool (``max_concurrency``).

Every answer text passes the redaction point before it is parsed, cached or returned (an
endpoint may echo the request headers). ``extra["parse_path"]`` says how the position was
read: ``structured`` (structured output), ``text`` (the text parser) or ``text_fallback``
(structured output was asked for but the endpoint refused or ignored it).
"""

from __future__ import annotations

import base64
import concurrent.futures as cf
import dataclasses
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.errors import ConfigError, DataError, ImageDecodeError
from vlm_vpr_ros.files.csvio import read_rows, unique_rows
from vlm_vpr_ros.files.images import check_rgb, decode_image_bytes, encode_jpeg
from vlm_vpr_ros.priors import register_prior_provider
from vlm_vpr_ros.priors.provider import KeyedTable, Prior, PriorProvider, PriorQuery, PriorResult
from vlm_vpr_ros.priors.cache import AnswerCache, cache_key, image_digest
from vlm_vpr_ros.priors.keys import read_api_key
from vlm_vpr_ros.priors.openai_client import CallHandle, ChatClient, ChatReply
from vlm_vpr_ros.priors.parsing import PARSER_MODES, parse_answer, parse_structured
from vlm_vpr_ros.priors.prompts import build_messages, get_prompt, response_format
from vlm_vpr_ros.priors.request import error_message, rejection, request_options
from vlm_vpr_ros.redact import redact, redact_obj

log = logging.getLogger(__name__)

__all__ = ["AnswersPrior", "OpenAIPrior", "read_answers_csv", "result_from_text"]


def result_from_text(raw: str | None, source: str, parser: str = "robust",
                     latency_s: float = 0.0, extra: dict[str, Any] | None = None,
                     parse_path: str = "text") -> PriorResult:
    """Parse a raw answer into a PriorResult: ok, a failure with the parser's reason, or
    ``suspicious_<why>`` for a position that must not be used as a prior. ``parse_path``
    ``structured`` reads a structured-output answer, falling back to the text parser."""
    # parsed as received, kept redacted: masking a short registered secret (a proxy user
    # name "7128") inside the answer would change "40.7128" before it is read
    text, raw = raw, (None if raw is None else redact(raw))
    parsed = parse_structured(text) if parse_path == "structured" else None
    if parsed is not None and parsed.reason == "no_coordinates":  # the schema was ignored
        parsed, parse_path = None, "text_fallback"
    if parsed is None:
        parsed = parse_answer(text, parser)
    extra = {**(extra or {}), "parser": parser, "parse_path": parse_path}
    if not parsed.ok:
        return PriorResult(None, source, parsed.reason, latency_s, raw, extra)
    assert parsed.lat is not None and parsed.lon is not None
    extra.update(parse_method=parsed.method, **redact_obj(parsed.info))
    if parsed.uncertainty_km is not None:
        extra["model_uncertainty_km"] = parsed.uncertainty_km
    if parsed.suspicious:  # read, but not a prior: flagged with the position for audit
        extra.update(suspicious=parsed.suspicious, answer_lat=parsed.lat,
                     answer_lon=parsed.lon)
        return PriorResult(None, source, f"suspicious_{parsed.suspicious}", latency_s, raw,
                           extra)
    return PriorResult(Prior(parsed.lat, parsed.lon, source), source, "", latency_s, raw, extra)


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


def _flag(value: Any, name: str) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.strip().lower() in ("true", "false", "1", "0", "yes",
                                                              "no", "on", "off"):
        return value.strip().lower() in ("true", "1", "yes", "on")
    raise ConfigError(f"openai prior: {name} must be true or false, got {value!r}")


class OpenAIPrior(PriorProvider):
    """Ask a VLM behind an OpenAI-compatible ``/chat/completions`` endpoint for a coarse
    position, with least-to-most prompting, robust parsing, retries, rate limiting and cache.

    Request fields follow the model family (:mod:`~vlm_vpr_ros.priors.request`):
    ``temperature`` and ``max_tokens`` default to ``auto``; ``token_param``,
    ``model_family``, ``reasoning_effort`` and ``extra_body`` override them.
    ``structured_output`` asks for a JSON-schema answer (``model_uncertainty`` adds the
    model's own error radius to the schema), falling back to text answers when the endpoint
    refuses it."""

    name = "openai"

    def __init__(self, base_url: str = "https://api.openai.com/v1", model: str = "gpt-4o",
                 api_key_env: str = "OPENAI_API_KEY", api_key_file: str | None = None,
                 timeout_s: float = 60.0, max_retries: int = 3, backoff_s: float = 1.0,
                 max_concurrency: int = 4, min_interval_s: float = 0.0,
                 temperature: Any = "auto", max_image_side: int | None = 1024,
                 parser: str = "robust", cache_dir: str | None = None, prompt: str = "ltm",
                 max_tokens: Any = "auto", token_param: str = "auto",
                 model_family: str = "auto", reasoning_effort: str | None = None,
                 extra_body: Any = None, structured_output: Any = False,
                 model_uncertainty: Any = False, auth_header: str = "auto",
                 ca_file: str | None = None) -> None:
        choose(parser, dict.fromkeys(PARSER_MODES), "answer parser")
        self.prompt = get_prompt(prompt)
        try:
            self.max_concurrency = int(max_concurrency)
            self.max_image_side = int(max_image_side) if max_image_side else None
            timeout_s, backoff_s = float(timeout_s), float(backoff_s)
            max_retries, min_interval_s = int(max_retries), float(min_interval_s)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"openai prior: invalid number ({exc}); timeout_s, backoff_s, "
                              "min_interval_s are seconds, max_retries, max_concurrency, "
                              "max_image_side integers") from None
        if self.max_concurrency < 1:
            raise ConfigError("openai prior: max_concurrency must be >= 1")
        if self.max_image_side is not None and self.max_image_side < 32:
            raise ConfigError("openai prior: max_image_side must be >= 32 (or null)")
        self.model = str(model)
        self.parser = parser
        self.structured = _flag(structured_output, "structured_output")
        uncertainty = _flag(model_uncertainty, "model_uncertainty")
        if uncertainty and not self.structured:
            raise ConfigError("openai prior: model_uncertainty needs structured_output=true")
        self.response_format = (response_format(self.prompt, uncertainty) if self.structured
                                else None)
        self.source = self.name = f"openai:{self.model}"  # name labels timeouts too
        key = read_api_key(api_key_env, api_key_file)
        self.client = ChatClient(base_url, key, timeout_s=timeout_s, max_retries=max_retries,
                                 backoff_s=backoff_s, min_interval_s=min_interval_s,
                                 auth_header=str(auth_header), ca_file=ca_file)
        self.options = request_options(
            self.model, self.client.endpoint, family=str(model_family),
            token_param=str(token_param), max_tokens=max_tokens, temperature=temperature,
            reasoning_effort=reasoning_effort, extra_body=extra_body)
        log.info("openai prior %s, model %s: %s%s", self.client.endpoint, self.model,
                 self.options.describe(), ", structured output" if self.structured else "")
        self.cache = AnswerCache(cache_dir) if cache_dir else None
        self._pool = cf.ThreadPoolExecutor(self.max_concurrency, thread_name_prefix="vlm-prior")
        self._lock = threading.Lock()
        self._pending: dict[cf.Future, CallHandle] = {}
        self._closed = False
        self._structured_refused = False
        self._told: set[str] = set()  # advice already logged (once per distinct line)

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
        self.client.close()

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
        answer_format = self.response_format["json_schema"]["name"] if self.structured else "text"
        key = cache_key(digest, self.model, self.prompt.id, self.client.endpoint, answer_format)
        extra: dict[str, Any] = {"model": self.model, "prompt": self.prompt.id,
                                 "image_sha256": digest, "cached": False}
        if self.cache is not None and (entry := self.cache.get(key)) is not None:
            extra["cached"] = True
            return result_from_text(entry["raw_text"], self.source, self.parser,
                                    time.monotonic() - t0, extra,
                                    str(entry.get("parse_path") or "text"))
        url = f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"
        reply, path = self._ask(build_messages(self.prompt, url), handle)
        latency = time.monotonic() - t0
        extra["attempts"] = reply.attempts
        if reply.reason == "refusal" and reply.refusal:
            extra["parse_path"] = path
            return PriorResult(None, self.source, "refusal", latency, redact(reply.refusal),
                               extra)
        if not reply.ok or reply.content is None:
            if detail := (self._explain(reply) or reply.detail):
                extra["detail"] = detail
                if detail == reply.detail:
                    self._tell(detail)
            return PriorResult(None, self.source, reply.reason or "bad_response", latency,
                               None, extra)
        result = result_from_text(reply.content, self.source, self.parser, latency, extra, path)
        if reply.finish_reason == "length" and (not result.ok and result.reason in (
                "empty", "no_coordinates") or result.extra.get("parse_path") != "structured"):
            # cut at the token limit: not the model's final answer, whatever it holds (a
            # guess it was still weighing): never a prior; a position read is kept for audit
            limit = f"{self.options.token_param}={self.options.max_tokens}"
            detail = (f"the answer was cut at {limit} before it was finished (reasoning "
                      "models spend tokens on hidden reasoning): not used; raise the prior "
                      "option max_tokens")
            self._tell(detail)
            audit = ({"answer_lat": result.prior.lat, "answer_lon": result.prior.lon}
                     if result.prior is not None else {})
            return PriorResult(None, self.source, "truncated", latency, result.raw_text,
                               {**result.extra, **audit, "detail": detail})
        if self.cache is not None:
            self.cache.put(key, reply.content, model=self.model, prompt=self.prompt.id,
                           image_sha256=digest, endpoint=self.client.endpoint,
                           parse_path=result.extra.get("parse_path", path))
        return result

    def _ask(self, messages: list[dict[str, Any]], handle: CallHandle) -> tuple[ChatReply, str]:
        """One call; structured output first when asked (once refused: text from then on).
        Returns the reply and the parse path its content takes."""
        structured = self.structured and not self._structured_refused
        body = self.options.body(self.model, messages,
                                 self.response_format if structured else None)
        reply = self.client.call(body, handle)
        if not structured:
            return reply, "text_fallback" if self.structured else "text"
        refused = rejection(reply.status or 0, reply.error_body or b"", body)
        if refused is None or refused.param != "response_format":
            return reply, "structured"
        self._structured_refused = True
        log.warning("%s refuses structured output (%s): reading text answers from now on",
                    self.client.endpoint, refused.message)
        again = self.client.call(self.options.body(self.model, messages), handle)
        return dataclasses.replace(again, attempts=reply.attempts + again.attempts), \
            "text_fallback"

    def _explain(self, reply: ChatReply) -> str | None:
        """One line for a request the endpoint refused (4xx): which option to change when it
        names a request field, else the server's own message (e.g. Ollama's "model ... not
        found, try pulling it first"). 401/403/407 are reported by the client."""
        status = reply.status or 0
        if not 400 <= status < 500 or status in (401, 403, 407, 408, 429):
            return None
        body = reply.error_body or b""
        refused = rejection(status, body, self.options.body(self.model, [],
                                                            self.response_format))
        detail = (refused.advice(self.client.endpoint, self.options) if refused is not None
                  else f"{self.client.endpoint}: HTTP {status} for model {self.model}: "
                       f"{error_message(body) or '(no message)'}")
        self._tell(detail)
        return detail

    def _tell(self, line: str) -> None:
        with self._lock:
            if line in self._told:
                return
            self._told.add(line)
        log.warning("%s", line)


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
        self._lookup = KeyedTable(self.answers)
        self.source = self.name = f"answers:{Path(path).stem}"

    def _compute(self, query: PriorQuery) -> PriorResult:
        if not query.key:
            return PriorResult.failure(self.source, "no_key")
        raw, why = self._lookup.find(query.key)
        if raw is None:
            return PriorResult.failure(self.source, why)
        return result_from_text(raw, self.source, self.parser)


register_prior_provider("openai", OpenAIPrior)
register_prior_provider("answers", AnswersPrior)
