"""Fault injection for the embedded server: every way a provider endpoint misbehaves.

| kind         | what the client sees                                                     |
|--------------|--------------------------------------------------------------------------|
| rate_limit   | 429 at once, with `Retry-After` (and `retry-after-ms` if fractional)      |
| overloaded   | 529 at once (Anthropic's "overloaded_error")                              |
| unavailable  | 503 at once                                                              |
| server_error | 500 after the usual latency                                              |
| slow         | a valid reply after `slow_s` (meant to exceed the client's timeout)      |
| malformed    | 200 after the latency with a body that is not valid JSON                 |
| truncated    | 200 whose body stops half-way and the connection closes                  |
| drop         | the connection closes after the latency without any response             |

Faults are drawn per request from `rates`, or taken in order from a script first (tests use
`plan.script("rate_limit", None)` for "a 429, then a normal reply").

A local inference server's own refusals (`server_config.ServerTraits`) are answered here too,
in vLLM's words and its error body (`vllm_refusal`, `vllm_error`), and a reasoning model's
refused parameters in OpenAI's (`reasoning_refusal`).
"""

from __future__ import annotations

import json
import math
import random
from collections import deque
from typing import Any, Literal, get_args

from aiohttp import web
from pydantic import BaseModel, ConfigDict, Field, model_validator

FaultKind = Literal[
    "rate_limit",
    "overloaded",
    "unavailable",
    "server_error",
    "slow",
    "malformed",
    "truncated",
    "drop",
]
FAULT_KINDS: tuple[str, ...] = get_args(FaultKind)
IMMEDIATE_FAULTS = frozenset({"rate_limit", "overloaded", "unavailable"})
_STATUS = {"rate_limit": 429, "overloaded": 529, "unavailable": 503, "server_error": 500}


class FaultConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    rates: dict[FaultKind, float] = Field(default_factory=dict)
    """Probability of each fault per request; they must add up to at most 1."""
    retry_after_s: float = Field(default=1.0, ge=0)
    """The wait announced with injected 429s."""
    slow_s: float = Field(default=30.0, ge=0)
    """How long a "slow" reply takes."""

    @model_validator(mode="after")
    def _rates_are_probabilities(self) -> FaultConfig:
        for kind, rate in self.rates.items():
            if not 0 <= rate <= 1:
                raise ValueError(f"rates.{kind} must be between 0 and 1, got {rate}")
        if sum(self.rates.values()) > 1 + 1e-9:
            raise ValueError(f"fault rates add up to {sum(self.rates.values()):.3f} > 1")
        return self


class FaultPlan:
    """Decides the fault (or None) for each incoming request."""

    def __init__(self, config: FaultConfig, rng: random.Random):
        self.config = config
        self._rng = rng
        self._script: deque[str | None] = deque()

    def script(self, *kinds: str | None) -> None:
        """The next requests get these faults, in order (None: a normal reply)."""
        for kind in kinds:
            if kind is not None and kind not in FAULT_KINDS:
                raise ValueError(f"unknown fault {kind!r}; valid faults: {list(FAULT_KINDS)}")
        self._script.extend(kinds)

    def next(self) -> str | None:
        if self._script:
            return self._script.popleft()
        draw = self._rng.random()
        for kind, rate in self.config.rates.items():
            if draw < rate:
                return kind
            draw -= rate
        return None


def retry_after_headers(seconds: float) -> dict[str, str]:
    """`Retry-After` in whole seconds (rounded up, as the header requires), plus the exact
    value in `retry-after-ms` when it is not whole."""
    headers = {"Retry-After": str(max(0, math.ceil(seconds)))}
    if seconds != int(seconds):
        headers["retry-after-ms"] = str(round(seconds * 1000))
    return headers


def error_response(
    status: int, body: dict[str, Any], headers: dict[str, str] | None = None
) -> web.Response:
    return web.Response(
        status=status, text=json.dumps(body), content_type="application/json", headers=headers
    )


def status_of(kind: str) -> int:
    return _STATUS[kind]


def malformed_response(good_body: dict[str, Any]) -> web.Response:
    text = json.dumps(good_body)
    return web.Response(status=200, text=text[: len(text) // 2], content_type="application/json")


async def truncated_response(request: web.Request, good_body: dict[str, Any]) -> web.StreamResponse:
    """Promise the whole body in Content-Length, send half, close the connection."""
    data = json.dumps(good_body).encode()
    resp = web.StreamResponse(status=200)
    resp.content_type = "application/json"
    resp.content_length = len(data)
    await resp.prepare(request)
    await resp.write(data[: len(data) // 2])
    if request.transport is not None:
        request.transport.close()
    return resp


def drop_connection(request: web.Request) -> web.Response:
    """Close the connection without a response (the returned object is never sent)."""
    if request.transport is not None:
        request.transport.close()
    return web.Response(status=500)


# -- a local inference server's refusals, as vLLM words them ----------------------------------


def vllm_refusal(
    model: str,
    served: str | None,
    images: int,
    max_images: int | None,
    prompt_tokens: int,
    max_output: int,
    max_model_len: int | None,
) -> tuple[int, str] | None:
    """vLLM's (status, message) for a request it refuses before generating, or None: an
    unknown model name (404), more images than `--limit-mm-per-prompt` allows, a prompt and
    output limit beyond `--max-model-len` (400)."""
    if served is not None and model != served:
        return 404, f"The model `{model}` does not exist."
    if max_images is not None and images > max_images:
        return 400, f"At most {max_images} image(s) may be provided in one request."
    if max_model_len is not None and prompt_tokens + max_output > max_model_len:
        return 400, (
            f"This model's maximum context length is {max_model_len} tokens. However, you "
            f"requested {prompt_tokens + max_output} tokens ({prompt_tokens} in the messages, "
            f"{max_output} in the completion). Please reduce the length of the messages or "
            "completion."
        )
    return None


def vllm_error(status: int, message: str) -> web.Response:
    """vLLM's error body: the message at the top level, beside its type and code."""
    kind = {404: "NotFoundError"}.get(status, "BadRequestError")
    body = {"object": "error", "message": message, "type": kind, "param": None, "code": status}
    return error_response(status, body)


def no_reasoning_refusal(body: dict[str, Any]) -> web.Response | None:
    """OpenAI's 400 for `reasoning_effort` sent to a model that does not reason, or None."""
    if body.get("reasoning_effort") is None and body.get("reasoning") is None:
        return None
    param = "reasoning_effort" if "reasoning_effort" in body else "reasoning.effort"
    error = {
        "message": f"Unsupported parameter: '{param}' is not supported with this model.",
        "type": "invalid_request_error",
        "param": param,
        "code": "unsupported_parameter",
    }
    return error_response(400, {"error": error})


def reasoning_refusal(body: dict[str, Any]) -> web.Response | None:
    """OpenAI's 400 for a parameter its reasoning models refuse (`max_tokens`, a `temperature`
    other than the default 1), or None."""
    if body.get("max_tokens") is not None:
        param, code = "max_tokens", "unsupported_parameter"
        message = (
            "Unsupported parameter: 'max_tokens' is not supported with this model. Use "
            "'max_completion_tokens' instead."
        )
    elif body.get("temperature") not in (None, 1):
        param, code = "temperature", "unsupported_value"
        message = (
            f"Unsupported value: 'temperature' does not support {body['temperature']} with this "
            "model. Only the default (1) value is supported."
        )
    else:
        return None
    error = {"message": message, "type": "invalid_request_error", "param": param, "code": code}
    return error_response(400, {"error": error})
