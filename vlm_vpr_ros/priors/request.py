"""What a chat-completions request carries, per provider and model family, and what a refusal
of one of its fields means for the user.

Endpoints disagree on request fields: OpenAI's reasoning models (``o1``, ``o3``, ``o4-mini``,
``gpt-5*``) reject ``max_tokens`` (they take ``max_completion_tokens``, which also bounds their
hidden reasoning tokens) and any ``temperature`` but the default; local servers (Ollama,
llama.cpp) know only ``max_tokens``; vLLM takes both. :func:`request_options` picks the
defaults from the model family and the host, every choice stays overridable by an option, and
:func:`rejection` turns an HTTP 400 that names a field into one line saying which option to
change.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from typing import Any, Mapping

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.redact import redact

__all__ = ["FAMILIES", "TOKEN_PARAMS", "RequestOptions", "error_message", "model_family",
           "rejection", "request_options"]

FAMILIES = ("auto", "chat", "reasoning")
TOKEN_PARAMS = ("auto", "max_tokens", "max_completion_tokens", "none")
#: OpenAI reasoning families, also behind Azure deployments named after the model; an optional
#: router prefix ("openai/o3") is allowed. gpt-5 "chat" variants are not reasoning models.
_REASONING = re.compile(r"^(?:[\w.-]+/)?(?:o[1-9]\d*(?:[-_.]\w[\w.-]*)?|gpt-5(?![\w.-]*chat)"
                        r"[\w.-]*)$", re.I)
#: endpoints that implement OpenAI's own request schema (max_completion_tokens for every
#: model): OpenAI and Azure OpenAI (its hosts, or its deployment / v1 routes on any host)
_OPENAI_SCHEMA = re.compile(r"^https?://(?:[^/?#]*[.@])?(?:api\.openai\.com|openai\.azure\.com|"
                            r"cognitiveservices\.azure\.com|services\.ai\.azure\.com)(?::\d+)?"
                            r"(?:[/?#]|$)|/openai/(?:deployments/|v1(?:/|$))", re.I)
DEFAULT_MAX_TOKENS = {"chat": 600, "reasoning": 4000}
#: fields the client owns: extra_body may not replace them
_RESERVED = frozenset({"messages", "stream", "n"})


def model_family(model: str) -> str:
    """``reasoning`` for OpenAI reasoning models (o-series, gpt-5*), else ``chat``."""
    return "reasoning" if _REASONING.match(model.strip()) else "chat"


@dataclass(frozen=True)
class RequestOptions:
    """The request fields besides the messages, resolved for one model and endpoint."""

    family: str  # "chat" or "reasoning"
    token_param: str  # "max_tokens", "max_completion_tokens" or "none"
    max_tokens: int
    temperature: float | None  # None: not sent
    reasoning_effort: str | None = None  # None: not sent
    extra_body: dict[str, Any] = field(default_factory=dict)

    def body(self, model: str, messages: list[dict[str, Any]],
             response_format: dict[str, Any] | None = None) -> dict[str, Any]:
        """The JSON body: model, messages, the resolved fields, then ``extra_body`` merged."""
        out: dict[str, Any] = {"model": model, "messages": messages}
        if self.token_param != "none":
            out[self.token_param] = self.max_tokens
        if self.temperature is not None:
            out["temperature"] = self.temperature
        if self.reasoning_effort is not None:
            out["reasoning_effort"] = self.reasoning_effort
        if response_format is not None:
            out["response_format"] = response_format
        out.update(self.extra_body)
        return out

    def describe(self) -> str:
        """One line for logs: what is sent besides the messages."""
        parts = [f"family {self.family}"]
        if self.token_param != "none":
            parts.append(f"{self.token_param}={self.max_tokens}")
        parts.append("no temperature" if self.temperature is None
                     else f"temperature={self.temperature:g}")
        if self.reasoning_effort is not None:
            parts.append(f"reasoning_effort={self.reasoning_effort}")
        if self.extra_body:
            parts.append(f"extra_body keys {sorted(self.extra_body)}")
        return ", ".join(parts)


def _extra_body(value: Any) -> dict[str, Any]:
    if value is None or value == "":
        return {}
    if isinstance(value, str):  # a ROS string parameter or a CLI value that was not JSON
        try:
            value = json.loads(value)
        except ValueError:
            raise ConfigError("openai prior: extra_body must be a JSON object, e.g. "
                              "'{\"top_k\": 20}'") from None
    if not isinstance(value, Mapping):
        raise ConfigError(f"openai prior: extra_body must be a JSON object, got "
                          f"{type(value).__name__}")
    reserved = sorted(_RESERVED & set(value))
    if reserved:
        raise ConfigError(f"openai prior: extra_body may not set {reserved} (the client "
                          "builds them)")
    return {str(k): v for k, v in value.items()}


def _temperature(value: Any, family: str) -> float | None:
    if value is None or (isinstance(value, str) and value.strip().lower() in ("none", "null",
                                                                               "off", "")):
        return None
    if isinstance(value, str) and value.strip().lower() == "auto":
        return None if family == "reasoning" else 0.0
    try:
        t = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"openai prior: temperature must be a number, 'auto' or 'none', got "
                          f"{value!r}") from None
    if not (math.isfinite(t) and 0.0 <= t <= 2.0):
        raise ConfigError(f"openai prior: temperature must be in [0, 2], got {value!r}")
    return t


def request_options(model: str, url: str, *, family: str = "auto", token_param: str = "auto",
                    max_tokens: Any = None, temperature: Any = "auto",
                    reasoning_effort: Any = None, extra_body: Any = None) -> RequestOptions:
    """Resolve the request options of ``model`` at the endpoint ``url`` (``auto``: by model
    family and endpoint)."""
    choose(str(family), dict.fromkeys(FAMILIES), "model_family")
    choose(str(token_param), dict.fromkeys(TOKEN_PARAMS), "token_param")
    fam = model_family(model) if family == "auto" else str(family)
    if token_param == "auto":
        openai_schema = fam == "reasoning" or bool(_OPENAI_SCHEMA.search(url or ""))
        token_param = "max_completion_tokens" if openai_schema else "max_tokens"
    if max_tokens is None or (isinstance(max_tokens, str) and max_tokens.lower() == "auto"):
        n = DEFAULT_MAX_TOKENS[fam]
    else:
        try:
            n = int(max_tokens)
        except (TypeError, ValueError):
            raise ConfigError(f"openai prior: max_tokens must be an integer, got "
                              f"{max_tokens!r}") from None
        if n < 1:
            raise ConfigError(f"openai prior: max_tokens must be >= 1, got {n}")
    effort = None if reasoning_effort in (None, "") else str(reasoning_effort).strip()
    if effort is not None and not re.fullmatch(r"[A-Za-z_-]{1,32}", effort):
        raise ConfigError(f"openai prior: reasoning_effort must be a word such as low, medium "
                          f"or high, got {reasoning_effort!r}")
    return RequestOptions(fam, str(token_param), n, _temperature(temperature, fam), effort,
                          _extra_body(extra_body))


# --- refusals ---------------------------------------------------------------------------------
_QUOTED = re.compile(r"['\"`‘’“”]([A-Za-z_][\w.\[\]]*)['\"`‘’“”]")


def _error_fields(payload: bytes) -> tuple[str, str | None]:
    """(message, param) of an error body in the OpenAI, vLLM or FastAPI shape."""
    text = payload[:20_000].decode("utf-8", "replace")
    try:
        body = json.loads(text)
    except (ValueError, RecursionError):
        return text, None
    err = body.get("error", body) if isinstance(body, dict) else body
    if isinstance(err, str):
        return err, None
    if isinstance(err, dict):
        param = err.get("param")
        msg = err.get("message") or err.get("detail") or text
        if isinstance(msg, list):  # FastAPI: [{"loc": ["body", "max_tokens"], "msg": ...}]
            locs = [d.get("loc") for d in msg if isinstance(d, dict)]
            names = [str(loc[-1]) for loc in locs if isinstance(loc, list) and loc]
            return json.dumps(msg)[:500], names[0] if names else None
        return str(msg), param if isinstance(param, str) else None
    return text, None


def _option_for(param: str, opts: RequestOptions) -> str:
    if param in ("max_tokens", "max_completion_tokens"):
        other = "max_tokens" if param == "max_completion_tokens" else "max_completion_tokens"
        return f"token_param={other} (or token_param=none)"
    if param == "temperature":
        return "temperature=none"
    if param == "reasoning_effort":
        return "reasoning_effort (a value the model supports, or unset it)"
    if param == "response_format":
        return "structured_output=false"
    if param.split(".")[0].split("[")[0] in opts.extra_body:
        return f"extra_body (remove or fix {param.split('.')[0]!r})"
    return "the request options (see docs/priors.md)"


def _one_line(message: str) -> str:
    one = " ".join(redact(message).split())
    return one[:197] + "..." if len(one) > 200 else one


def error_message(payload: bytes) -> str:
    """The server's message in an error body, redacted, on one line of <= 200 characters."""
    return _one_line(_error_fields(payload)[0])


@dataclass(frozen=True)
class Rejection:
    """An HTTP 4xx that names a request field: which one, and the one-line advice."""

    param: str
    message: str  # the server's message, redacted, one line, at most 200 characters

    def advice(self, endpoint: str, opts: RequestOptions) -> str:
        return (f"{endpoint} rejects the request field {self.param!r} ({self.message}): change "
                f"the prior option {_option_for(self.param, opts)}")


def rejection(status: int, payload: bytes, sent: Mapping[str, Any]) -> Rejection | None:
    """The field an HTTP 400/422 names among the top-level fields ``sent``, or None."""
    if status not in (400, 422):
        return None
    message, param = _error_fields(payload)
    top = param.split(".")[0].split("[")[0] if param else None
    if top not in sent:
        named = [m.group(1) for m in _QUOTED.finditer(message)]
        named += re.findall(r"\b(response_format|json_schema|max_completion_tokens|max_tokens|"
                            r"temperature|reasoning_effort)\b", message)
        top = next((n.split(".")[0].split("[")[0] for n in named
                    if n.split(".")[0].split("[")[0] in sent and n != "model"), None)
        if top is None and "json_schema" in named and "response_format" in sent:
            top = "response_format"
    if top is None or top in ("messages", "model"):
        return None
    return Rejection(top, _one_line(message))
