"""What the two OpenAI APIs (Chat Completions and Responses) share: base URLs up to `/v1`,
the key as a bearer token, the options they take (`reasoning_effort`, not `thinking_budget`),
the image token rule, automatic prompt caching, error bodies at `error.{message,type}`,
`x-ratelimit-*` headers with Go-duration resets, and usage that counts cache reads and writes
*inside* the prompt tokens and reasoning inside the output tokens (each API names the fields
its own way, so each keeps its usage model and reads it with `usage_of`).
"""

from __future__ import annotations

import math
from typing import Any

from vabench.llm_pool.apis.base import (
    ApiAdapter,
    LooseModel,
    RequestT,
    ResponseT,
)
from vabench.llm_pool.messages import Usage
from vabench.llm_pool.settings import ConfigError, GenerationOptions
from vabench.llm_pool.tokens import openai_image_tokens

_ERROR_TYPES = {
    400: "invalid_request_error",
    401: "invalid_api_key",
    403: "permission_denied",
    404: "not_found",
    429: "rate_limit_exceeded",
}


class PromptDetails(LooseModel):
    """`prompt_tokens_details` (Chat Completions), `input_tokens_details` (Responses)."""

    cached_tokens: int | None = None
    cache_write_tokens: int | None = None


class OutputDetails(LooseModel):
    """`completion_tokens_details` (Chat Completions), `output_tokens_details` (Responses)."""

    reasoning_tokens: int | None = None


def usage_of(
    prompt_tokens: int,
    prompt: PromptDetails | None,
    output_tokens: int,
    output: OutputDetails | None,
) -> Usage:
    """Our split of OpenAI usage: the cached and written tokens come out of the prompt's."""
    prompt = prompt or PromptDetails()
    cached, written = prompt.cached_tokens or 0, prompt.cache_write_tokens or 0
    return Usage(
        input_tokens=max(0, prompt_tokens - cached - written),
        cached_input_tokens=cached,
        cache_write_tokens=written,
        output_tokens=output_tokens,
        reasoning_tokens=output.reasoning_tokens if output is not None else None,
    )


def prompt_details(usage: Usage) -> dict[str, int]:
    """The prompt details a server reports beside `usage.prompt_tokens`, which includes them."""
    return {
        "cached_tokens": usage.cached_input_tokens,
        "cache_write_tokens": usage.cache_write_tokens,
    }


def output_details(usage: Usage) -> dict[str, int]:
    """OpenAI reports 0 reasoning tokens for a call that did not reason."""
    return {"reasoning_tokens": usage.reasoning_tokens or 0}


def go_duration(seconds: float) -> str:
    """Seconds as OpenAI writes them in reset headers: `20ms`, `1.5s`, `6m0s`."""
    if seconds < 1:
        return f"{max(0, math.ceil(seconds * 1000))}ms"
    minutes, secs = divmod(seconds, 60)
    secs_text = f"{secs:.3f}".rstrip("0").rstrip(".")
    return f"{int(minutes)}m{secs_text}s" if minutes else f"{secs_text}s"


class OpenAIApi(ApiAdapter[RequestT, ResponseT]):
    """The parts of an adapter both OpenAI APIs write the same way."""

    default_host = "https://api.openai.com"
    base_path = "/v1"
    prompt_caching = "automatic"
    rate_limit_header = "x-ratelimit-{field}-{limit}"

    def image_tokens(self, width: int, height: int) -> int:
        return openai_image_tokens(width, height)

    def check_options(self, options: GenerationOptions) -> None:
        if options.sent_thinking_budget is not None:
            raise ConfigError(
                "generation.thinking_budget", "anthropic only; use reasoning_effort for OpenAI"
            )

    def url(self, base_url: str) -> str:
        # an OpenAI base URL ends in /v1 (`ModelEndpoint.base_url`), the route starts with it
        return base_url + self.route.removeprefix(self.base_path)

    def error_body(self, status: int, message: str) -> dict[str, Any]:
        error_type = _ERROR_TYPES.get(status, "server_error")
        return {"error": {"message": message, "type": error_type, "param": None, "code": None}}

    def reset_text(self, seconds: float) -> str:
        return go_duration(seconds)
