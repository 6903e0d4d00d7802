"""TEST FIXTURE: what the loopback chat server (tests/chat_server.py) checks per dialect.

Each dialect reproduces the routes, the authentication and the error bodies of the real server
as documented (late 2026), so that the client meets them the way it would in the field:

``openai``
    ``/v1/chat/completions``, ``Authorization: Bearer`` when a key is demanded; 401
    ``invalid_api_key``.
``openai_reasoning``
    ``openai`` for a reasoning model (o-series, gpt-5*): 400 ``unsupported_parameter`` for
    ``max_tokens`` ("Use 'max_completion_tokens' instead"), 400 ``unsupported_value`` for a
    ``temperature`` other than 1, 400 for an unknown ``reasoning_effort``.
``azure``
    ``/openai/deployments/<deployment>/chat/completions?api-version=<version>`` (404 "Resource
    not found" without it, 400 for an unknown version), the key in the ``api-key`` header (401
    "Access denied ..." otherwise); the deployment behaves as the reasoning model it serves.
``ollama``
    ``/v1/chat/completions``, no authentication, 404 "model ... not found, try pulling it
    first" for a model it does not have; unknown fields are ignored.
``vllm``
    ``/v1/chat/completions``, ``Authorization: Bearer`` when started with ``--api-key`` (401
    ``{"error": "Unauthorized"}``), 404 ``NotFoundError`` for another model name, errors in
    vLLM's ``{"object": "error", ...}`` shape.
"""

from __future__ import annotations

import json
import urllib.parse
from typing import Any

DIALECTS = ("openai", "openai_reasoning", "azure", "ollama", "vllm")
AZURE_API_VERSIONS = ("2024-10-21", "2025-04-01-preview")
REASONING_EFFORTS = ("none", "minimal", "low", "medium", "high", "xhigh")

Problem = tuple[int, dict[str, Any]]


def _openai_error(message: str, param: str | None, code: str,
                  kind: str = "invalid_request_error") -> dict[str, Any]:
    return {"error": {"message": message, "type": kind, "param": param, "code": code}}


def route_problem(dialect: str, path: str, headers: dict[str, str], api_key: str | None,
                  deployment: str) -> Problem | None:
    """404/401/400 for a request the dialect would refuse before reading the body."""
    parts = urllib.parse.urlsplit(path)
    query = dict(urllib.parse.parse_qsl(parts.query))
    low = {k.lower(): v for k, v in headers.items()}
    if dialect == "azure":
        if parts.path != f"/openai/deployments/{deployment}/chat/completions":
            return 404, {"error": {"code": "DeploymentNotFound", "message":
                                   "The API deployment for this resource does not exist."}}
        if "api-version" not in query:
            return 404, {"error": {"code": "404", "message": "Resource not found"}}
        if query["api-version"] not in AZURE_API_VERSIONS:
            return 400, {"error": {"code": "BadRequest", "message":
                                   "API version not supported"}}
        if api_key is not None and low.get("api-key") != api_key:
            return 401, {"error": {"code": "401", "message": (
                "Access denied due to invalid subscription key or wrong API endpoint. Make "
                "sure to provide a valid key for an active subscription and use a correct "
                "regional API endpoint for your resource.")}}
        return None
    if not parts.path.rstrip("/").endswith("/v1/chat/completions"):
        return 404, {"error": {"message": f"no route {parts.path}"}}
    if api_key is None or dialect == "ollama":
        return None
    if low.get("authorization") != f"Bearer {api_key}":
        if dialect == "vllm":
            return 401, {"error": "Unauthorized"}
        return 401, _openai_error("Incorrect API key provided. You can find your API key at "
                                  "https://platform.openai.com/account/api-keys.", None,
                                  "invalid_api_key")
    return None


def _reasoning_problem(body: dict[str, Any]) -> Problem | None:
    if "max_tokens" in body:
        return 400, _openai_error("Unsupported parameter: 'max_tokens' is not supported with "
                                  "this model. Use 'max_completion_tokens' instead.",
                                  "max_tokens", "unsupported_parameter")
    t = body.get("temperature")
    if t is not None and t != 1:
        return 400, _openai_error(f"Unsupported value: 'temperature' does not support {t} with "
                                  "this model. Only the default (1) value is supported.",
                                  "temperature", "unsupported_value")
    effort = body.get("reasoning_effort")
    if effort is not None and effort not in REASONING_EFFORTS:
        return 400, _openai_error(f"Unsupported value: 'reasoning_effort' does not support "
                                  f"{effort!r} with this model. Supported values are: "
                                  f"{', '.join(map(repr, REASONING_EFFORTS))}.",
                                  "reasoning_effort", "unsupported_value")
    return None


def body_problem(dialect: str, body: dict[str, Any], models: tuple[str, ...] | None,
                 structured: bool | str) -> Problem | None:
    """400/404 for a body the dialect refuses."""
    model = str(body.get("model", ""))
    if models is not None and model not in models:
        if dialect == "ollama":
            return 404, {"error": {"message": f'model "{model}" not found, try pulling it '
                                              "first", "type": "api_error", "param": None,
                                   "code": None}}
        if dialect == "vllm":
            return 404, {"object": "error", "message": f"The model `{model}` does not exist.",
                         "type": "NotFoundError", "param": None, "code": 404}
        return 404, _openai_error(f"The model `{model}` does not exist or you do not have "
                                  "access to it.", None, "model_not_found")
    if dialect in ("openai_reasoning", "azure"):
        problem = _reasoning_problem(body)
        if problem is not None:
            return problem
    rf = body.get("response_format")
    if isinstance(rf, dict) and rf.get("type") == "json_schema" and structured is False:
        if dialect == "vllm":
            return 400, {"object": "error", "message": "response_format json_schema is not "
                         "supported by this server", "type": "BadRequestError", "param": None,
                         "code": 400}
        return 400, _openai_error("Invalid parameter: 'response_format' of type 'json_schema' "
                                  "is not supported with this model.", "response_format",
                                  "invalid_parameter")
    return None


def structured_answer(json_schema: dict[str, Any], lat: float, lon: float,
                      uncertainty_km: float) -> str:
    """The JSON object a model constrained by ``json_schema`` would write."""
    props = (json_schema.get("schema") or {}).get("properties") or {}
    out: dict[str, Any] = {}
    for name, spec in props.items():
        if name == "latitude":
            out[name] = lat
        elif name == "longitude":
            out[name] = lon
        elif name == "uncertainty_km":
            out[name] = uncertainty_km
        elif spec.get("type") == "string":
            out[name] = f"fixture {name}"
    return json.dumps(out)
