"""Anthropic Messages (`POST {host}/v1/messages`).

Request: headers `anthropic-version` and the key as `Authorization: Bearer` (what the official
SDK sends; the API also takes `x-api-key`); the system prompt is the top-level `system` field;
user content is a list of `{"type":"text"}` and
`{"type":"image","source":{"type":"base64","media_type":"image/jpeg","data":"..."}}` blocks;
`max_tokens` is required; extended thinking is `thinking: {"type":"enabled","budget_tokens":N}`
(N >= 1024 and below max_tokens). This API version takes no `temperature` (the SDK's message
parameters have none), so vabench never sends one and refuses it in an anthropic model's
`generation` (`Anthropic.check_options`).

Prompt caching is opt-in through `cache_control: {"type":"ephemeral"}` markers. vabench puts
one on the system prompt (the prefix that never changes within a task) and one on the last
block of the last user turn, so the next call of the same episode reads the whole earlier
conversation from the cache (Anthropic looks back from a marker for the longest cached
prefix). Markers on prefixes shorter than the model's minimum (1,024 or 2,048 tokens) are
ignored by the API at no cost.

Response: `content` blocks (`thinking` and `redacted_thinking` go to the reasoning, `text`
blocks are joined as the answer, `tool_use` blocks are function calls), `stop_reason`
(`end_turn`, `max_tokens`, `stop_sequence`, `refusal`, `tool_use`, ...), a `request-id`
header. Usage: `input_tokens` *excludes*
cache reads (`cache_read_input_tokens`) and cache writes (`cache_creation_input_tokens`);
`output_tokens` includes thinking, reported apart in `output_tokens_details.thinking_tokens`.
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping
from datetime import datetime, timedelta, timezone
from typing import Annotated, Any, Literal

from pydantic import Field

from vabench.llm_pool.apis import base
from vabench.llm_pool.messages import ChatRequest, FinishReason, FunctionCall, Part, Turn, Usage
from vabench.llm_pool.settings import ConfigError, GenerationOptions
from vabench.llm_pool.tokens import anthropic_image_tokens

ANTHROPIC_VERSION = "2026-10-21"
"""The `anthropic-version` the official SDK (anthropic 2.13) sends."""
_EPHEMERAL = {"type": "ephemeral"}

# -- request shape ----------------------------------------------------------------------------


class _CacheControl(base.StrictModel):
    type: Literal["ephemeral"]
    ttl: Literal["5m", "1h"] | None = None


class _TextBlock(base.ContentPart):
    type: Literal["text"]
    text: str
    cache_control: _CacheControl | None = None

    def part(self, field: str) -> Part:
        return self.text


class _Base64Source(base.StrictModel):
    type: Literal["base64"]
    media_type: Literal["image/jpeg", "image/png", "image/gif", "image/webp"]
    data: str


class _ImageBlock(base.ContentPart):
    type: Literal["image"]
    source: _Base64Source
    cache_control: _CacheControl | None = None

    def part(self, field: str) -> Part:
        return base.base64_image(self.source.data, self.source.media_type, f"{field}.source.data")


_Block = Annotated[_TextBlock | _ImageBlock, Field(discriminator="type")]


class _Message(base.StrictModel):
    role: Literal["user", "assistant"]
    content: str | list[_Block] = Field(min_length=1)


class _ThinkingEnabled(base.StrictModel):
    type: Literal["enabled"]
    budget_tokens: int = Field(ge=1024)
    display: Literal["summarized", "omitted"] | None = None


class _ThinkingAdaptive(base.StrictModel):
    type: Literal["adaptive"]
    display: Literal["summarized", "omitted"] | None = None


class _ThinkingDisabled(base.StrictModel):
    type: Literal["disabled"]


_Thinking = Annotated[
    _ThinkingEnabled | _ThinkingAdaptive | _ThinkingDisabled, Field(discriminator="type")
]


class _Metadata(base.StrictModel):
    user_id: str | None = None


class MessagesRequest(base.RequestBody):
    """What the embedded server takes: the parameters a text-and-image call uses (no tools,
    containers or streaming: vabench sends none of them). `temperature`, `top_p` and `top_k`
    are still taken from clients of earlier API versions."""

    max_tokens: int = Field(ge=1)
    messages: list[_Message] = Field(min_length=1)
    system: str | list[_TextBlock] | None = None
    temperature: float | None = Field(default=None, ge=0, le=1)
    top_p: float | None = Field(default=None, ge=0, le=1)
    top_k: int | None = Field(default=None, ge=0)
    stop_sequences: list[str] | None = None
    thinking: _Thinking | None = None
    stream: Literal[False] | None = None
    metadata: _Metadata | None = None
    service_tier: Literal["auto", "standard_only"] | None = None


# -- response shape ---------------------------------------------------------------------------


class _ContentBlock(base.LooseModel):
    type: str
    text: str | None = None
    thinking: str | None = None
    name: str | None = None
    input: dict[str, Any] | None = None


class _OutputDetails(base.LooseModel):
    thinking_tokens: int | None = None


class _Usage(base.UsageBody):
    input_tokens: int
    output_tokens: int
    cache_creation_input_tokens: int | None = None
    cache_read_input_tokens: int | None = None
    output_tokens_details: _OutputDetails | None = None

    def to_usage(self) -> Usage:
        details = self.output_tokens_details
        return Usage(
            input_tokens=self.input_tokens,
            cached_input_tokens=self.cache_read_input_tokens or 0,
            cache_write_tokens=self.cache_creation_input_tokens or 0,
            output_tokens=self.output_tokens,
            reasoning_tokens=details.thinking_tokens if details is not None else None,
        )


class MessagesResponse(base.ResponseBody):
    content: list[_ContentBlock]
    stop_reason: str | None = None
    usage: _Usage | None = None


_FINISH: dict[str, FinishReason] = {
    "end_turn": "stop",
    "stop_sequence": "stop",
    "max_tokens": "length",
    "model_context_window_exceeded": "length",
    "refusal": "refusal",
}
_STOP_REASON: dict[FinishReason, str] = {
    "stop": "end_turn",
    "length": "max_tokens",
    "refusal": "refusal",
    "content_filter": "refusal",
    "other": "end_turn",
}
_ERROR_TYPES = {
    400: "invalid_request_error",
    401: "authentication_error",
    403: "permission_error",
    404: "not_found_error",
    413: "request_too_large",
    429: "rate_limit_error",
    529: "overloaded_error",
}


def rfc3339_in(seconds: float) -> str:
    when = datetime.now(timezone.utc) + timedelta(seconds=seconds)
    return when.isoformat(timespec="milliseconds").replace("+00:00", "Z")


class Anthropic(base.ApiAdapter[MessagesRequest, MessagesResponse]):
    name = "anthropic"
    reasoning_option = "thinking_budget"
    route = "/v1/messages"
    default_host = "https://api.anthropic.com"
    base_path = ""
    prompt_caching = "explicit"
    request_model = MessagesRequest
    response_model = MessagesResponse
    response_label = "messages"
    rate_limit_header = "anthropic-ratelimit-{limit}-{field}"
    request_id_header = "request-id"

    def image_tokens(self, width: int, height: int) -> int:
        return anthropic_image_tokens(width, height)

    def check_options(self, options: GenerationOptions) -> None:
        if options.temperature is not None:
            raise ConfigError(
                "generation.temperature",
                "the Anthropic Messages API (version 2026-10-21, the official SDK's) takes no "
                "temperature; remove it (it applies to the OpenAI APIs only)",
            )
        if options.sent_reasoning_effort is not None:
            raise ConfigError(
                "generation.reasoning_effort", "OpenAI only; use thinking_budget for anthropic"
            )
        budget = options.sent_thinking_budget
        if budget is not None and budget >= options.resolved_max_output_tokens:
            raise ConfigError(
                "generation.thinking_budget",
                f"must be below max_output_tokens ({options.resolved_max_output_tokens})",
            )

    def url(self, base_url: str) -> str:
        return f"{base_url}/messages" if base_url.endswith("/v1") else f"{base_url}/v1/messages"

    def headers(self, api_key: str | None) -> dict[str, str]:
        return {"anthropic-version": ANTHROPIC_VERSION, **super().headers(api_key)}

    def build_body(
        self, endpoint: base.Endpoint, request: ChatRequest, options: GenerationOptions
    ) -> dict[str, Any]:
        cache = options.cache_prompt is not False
        messages = self.messages(request)
        if cache:
            messages[-1]["content"][-1]["cache_control"] = _EPHEMERAL
        body: dict[str, Any] = {
            "model": endpoint.provider_model,
            "max_tokens": options.resolved_max_output_tokens,
            "messages": messages,
        }
        if request.system:
            body["system"] = (
                [{"type": "text", "text": request.system, "cache_control": _EPHEMERAL}]
                if cache
                else request.system
            )
        if options.sent_thinking_budget is not None:
            body["thinking"] = {"type": "enabled", "budget_tokens": options.sent_thinking_budget}
        return body

    def part(self, part: Part) -> dict[str, Any]:
        if isinstance(part, str):
            return {"type": "text", "text": part}
        source = {
            "type": "base64",
            "media_type": part.media_type,
            "data": base.InlineImage(part, data_url=False),
        }
        return {"type": "image", "source": source}

    def read_answer(self, body: MessagesResponse) -> base.Answer:
        texts = [b.text for b in body.content if b.type == "text" and b.text is not None]
        thoughts = [b.thinking for b in body.content if b.type == "thinking" and b.thinking]
        if any(b.type == "redacted_thinking" for b in body.content):
            thoughts.append("[redacted thinking]")
        calls = tuple(
            FunctionCall(b.name or "", b.input or {}) for b in body.content if b.type == "tool_use"
        )
        return base.Answer(
            text="".join(texts),
            finish_reason=_FINISH.get(body.stop_reason or "", "other"),
            raw_finish_reason=body.stop_reason,
            usage=body.usage,
            reasoning=base.join_reasoning(*thoughts),
            function_calls=calls,
        )

    def parse_request(self, raw: bytes, headers: Mapping[str, str]) -> base.IncomingRequest:
        if not headers.get("anthropic-version"):
            raise base.RequestShapeError("anthropic-version", "header is required")
        return super().parse_request(raw, headers)

    def read_request(self, body: MessagesRequest) -> base.Prompt:
        budget: int | None = None
        if isinstance(body.thinking, _ThinkingEnabled):
            budget = body.thinking.budget_tokens
            if budget >= body.max_tokens:
                raise base.RequestShapeError(
                    "thinking.budget_tokens", "must be less than max_tokens"
                )
            if body.temperature not in (None, 1.0):
                raise base.RequestShapeError(
                    "temperature", "may only be set to 1 when thinking is enabled"
                )
        breakpoints: list[int] = []
        system: str | None = None
        if isinstance(body.system, str):
            system = body.system or None
        elif body.system:
            system = "\n".join(b.text for b in body.system) or None
            if system and any(b.cache_control for b in body.system):
                breakpoints.append(0)
        index = 1 if system else 0  # position in chat.blocks
        turns: list[Turn] = []
        for i, m in enumerate(body.messages):
            if isinstance(m.content, str):
                blocks: list[_TextBlock | _ImageBlock] = [_TextBlock(type="text", text=m.content)]
            else:
                blocks = list(m.content)
            parts: list[Part] = []
            for j, b in enumerate(blocks):
                field = f"messages.{i}.content.{j}"
                if isinstance(b, _ImageBlock) and m.role == "assistant":
                    raise base.RequestShapeError(field, "images in assistant turn")
                parts.append(b.part(field))
                if b.cache_control is not None:
                    breakpoints.append(index)
                index += 1
            turns.append(Turn(m.role, tuple(parts)))
        if len(breakpoints) > 4:
            raise base.RequestShapeError("cache_control", "at most 4 blocks may have cache_control")
        options = GenerationOptions(
            max_output_tokens=body.max_tokens,
            temperature=body.temperature,
            thinking_budget=budget,
        )
        return base.Prompt(turns, system, options, tuple(breakpoints))

    def build_response(self, reply: base.ServerReply) -> dict[str, Any]:
        content: list[dict[str, Any]] = []
        if reply.reasoning:
            signature = uuid.uuid4().hex
            content.append(
                {"type": "thinking", "thinking": reply.reasoning, "signature": signature}
            )
        content.append({"type": "text", "text": reply.text})
        u = reply.usage
        return {
            "id": f"msg_{uuid.uuid4().hex[:24]}",
            "type": "message",
            "role": "assistant",
            "model": reply.model,
            "content": content,
            "stop_reason": _STOP_REASON[reply.finish_reason],
            "stop_sequence": None,
            "usage": {
                "input_tokens": u.input_tokens,
                "cache_creation_input_tokens": u.cache_write_tokens,
                "cache_read_input_tokens": u.cached_input_tokens,
                "output_tokens": u.output_tokens,
                **(
                    {"output_tokens_details": {"thinking_tokens": u.reasoning_tokens}}
                    if u.reasoning_tokens is not None
                    else {}
                ),
            },
        }

    def error_body(self, status: int, message: str) -> dict[str, Any]:
        error_type = _ERROR_TYPES.get(status, "api_error")
        return {"type": "error", "error": {"type": error_type, "message": message}}

    def reset_text(self, seconds: float) -> str:
        return rfc3339_in(seconds)

    def server_key(self, headers: Mapping[str, str]) -> str | None:
        """`x-api-key`, or a bearer token (what the SDK sends for a key and an auth token)."""
        return headers.get("x-api-key") or super().server_key(headers)
