"""OpenAI Chat Completions (`POST {base}/chat/completions`), and every OpenAI-compatible
server (vLLM, SGLang, Ollama, llama.cpp) through the same path.

Request: the system prompt is the first message (`role: system`); user content is a list of
`{"type":"text"}` and `{"type":"image_url","image_url":{"url":"data:image/jpeg;base64,..."}}`
parts; assistant turns are plain strings. The output limit goes in `max_completion_tokens`
(or `max_tokens`, see `ModelEndpoint.max_tokens_field`), `reasoning_effort` is top-level.

Response: `choices[0].message.content`, `finish_reason`; usage `prompt_tokens` *includes*
`prompt_tokens_details.cached_tokens`; `completion_tokens` includes
`completion_tokens_details.reasoning_tokens`. vLLM and SGLang return a reasoning model's
thoughts in `message.reasoning_content`.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Mapping
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from vabench.llm_pool.apis.base import (
    ApiAdapter,
    IncomingRequest,
    InlineImage,
    LimitState,
    RequestShapeError,
    ServerReply,
    openai_error_type,
    openai_rate_limit_headers,
    openai_usage,
    parse_data_url,
    usage_from_openai,
    validate_request_json,
    validate_response_json,
)
from vabench.llm_pool.config import GenerationOptions, ModelEndpoint, ReasoningEffort
from vabench.llm_pool.messages import (
    ChatRequest,
    FinishReason,
    ParsedResponse,
    Part,
    Turn,
    Usage,
)
from vabench.llm_pool.tokens import openai_image_tokens

# -- request shape (as documented; the embedded server validates against it) ----------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class _TextPart(_Strict):
    type: Literal["text"]
    text: str


class _ImageURL(_Strict):
    url: str
    detail: Literal["auto", "low", "high"] | None = None


class _ImagePart(_Strict):
    type: Literal["image_url"]
    image_url: _ImageURL


_ContentPart = Annotated[_TextPart | _ImagePart, Field(discriminator="type")]


class _Message(_Strict):
    role: Literal["system", "developer", "user", "assistant"]
    content: str | list[_ContentPart]
    name: str | None = None


class _ResponseFormat(_Strict):
    type: Literal["text", "json_object", "json_schema"]
    json_schema: dict[str, Any] | None = None


class ChatCompletionsRequest(_Strict):
    """What the embedded server takes: the parameters a text-and-image call uses (no tools,
    audio, logprobs or streaming: vabench sends none of them, and none is served)."""

    model: str = Field(min_length=1)
    messages: list[_Message] = Field(min_length=1)
    max_completion_tokens: int | None = Field(default=None, ge=1)
    max_tokens: int | None = Field(default=None, ge=1)
    temperature: float | None = Field(default=None, ge=0, le=2)
    top_p: float | None = Field(default=None, ge=0, le=1)
    frequency_penalty: float | None = Field(default=None, ge=-2, le=2)
    presence_penalty: float | None = Field(default=None, ge=-2, le=2)
    stop: str | list[str] | None = None
    response_format: _ResponseFormat | None = None
    reasoning_effort: ReasoningEffort | None = None
    stream: Literal[False] | None = None
    n: Literal[1] | None = None
    seed: int | None = None
    user: str | None = None
    metadata: dict[str, str] | None = None
    store: bool | None = None
    prompt_cache_key: str | None = None
    service_tier: str | None = None


# -- response shape (lenient: unknown fields are ignored, required ones are checked) ---------


class _Loose(BaseModel):
    model_config = ConfigDict(extra="ignore")


class _PromptDetails(_Loose):
    cached_tokens: int | None = None
    cache_write_tokens: int | None = None


class _CompletionDetails(_Loose):
    reasoning_tokens: int | None = None


class _Usage(_Loose):
    prompt_tokens: int
    completion_tokens: int
    prompt_tokens_details: _PromptDetails | None = None
    completion_tokens_details: _CompletionDetails | None = None


class _AnswerMessage(_Loose):
    content: str | None = None
    refusal: str | None = None
    reasoning_content: str | None = None


class _Choice(_Loose):
    message: _AnswerMessage
    finish_reason: str | None = None


class ChatCompletionsResponse(_Loose):
    id: str | None = None
    model: str | None = None
    choices: list[_Choice] = Field(min_length=1)
    usage: _Usage | None = None


_FINISH: dict[str, FinishReason] = {
    "stop": "stop",
    "length": "length",
    "content_filter": "content_filter",
}


def _openai_finish(finish: FinishReason) -> str:
    # OpenAI reports a refusal in message.refusal with finish_reason "stop".
    return "stop" if finish == "refusal" else finish


def _part(part: Part) -> dict[str, Any]:
    if isinstance(part, str):
        return {"type": "text", "text": part}
    return {"type": "image_url", "image_url": {"url": InlineImage(part, data_url=True)}}


def _text_of(content: str | list[_ContentPart], field: str) -> str:
    if isinstance(content, str):
        return content
    texts = []
    for i, p in enumerate(content):
        if not isinstance(p, _TextPart):
            raise RequestShapeError(f"{field}.{i}", "only text parts are allowed in this role")
        texts.append(p.text)
    return "\n".join(texts)


class OpenAIChat(ApiAdapter):
    name = "openai_chat"
    route = "/v1/chat/completions"

    def image_tokens(self, width: int, height: int) -> int:
        return openai_image_tokens(width, height)

    def url(self, base_url: str) -> str:
        return f"{base_url}/chat/completions"

    def headers(self, api_key: str | None) -> dict[str, str]:
        return {"Authorization": f"Bearer {api_key}"} if api_key else {}

    def build_body(
        self, endpoint: ModelEndpoint, request: ChatRequest, options: GenerationOptions
    ) -> dict[str, Any]:
        messages: list[dict[str, Any]] = []
        if request.system:
            messages.append({"role": "system", "content": request.system})
        for turn in request.turns:
            if turn.role == "assistant":
                messages.append({"role": "assistant", "content": turn.text})
            else:
                messages.append({"role": "user", "content": [_part(p) for p in turn.content]})
        body: dict[str, Any] = {
            "model": endpoint.provider_model,
            "messages": messages,
            endpoint.max_tokens_field: options.resolved_max_output_tokens,
        }
        if options.temperature is not None:
            body["temperature"] = options.temperature
        if options.reasoning_effort is not None:
            body["reasoning_effort"] = options.reasoning_effort
        return body

    def parse_response(self, raw: bytes) -> ParsedResponse:
        body = validate_response_json(ChatCompletionsResponse, raw, "chat completions")
        choice = body.choices[0]
        message = choice.message
        finish: FinishReason = _FINISH.get(choice.finish_reason or "", "other")
        if message.refusal:
            finish = "refusal"
        u = body.usage
        usage = Usage()
        if u is not None:
            prompt = u.prompt_tokens_details or _PromptDetails()
            usage = usage_from_openai(
                u.prompt_tokens,
                prompt.cached_tokens,
                u.completion_tokens,
                u.completion_tokens_details.reasoning_tokens
                if u.completion_tokens_details
                else None,
                prompt.cache_write_tokens,
            )
        return ParsedResponse(
            text=message.content or message.refusal or "",
            finish_reason=finish,
            raw_finish_reason=choice.finish_reason,
            usage=usage,
            model=body.model,
            response_id=body.id,
            reasoning=message.reasoning_content,
            usage_reported=u is not None,
        )

    def parse_request(self, raw: bytes, headers: Mapping[str, str]) -> IncomingRequest:
        body = validate_request_json(ChatCompletionsRequest, raw)
        if body.max_tokens is not None and body.max_completion_tokens is not None:
            raise RequestShapeError(
                "max_tokens", "set max_tokens or max_completion_tokens, not both"
            )
        system: list[str] = []
        turns: list[Turn] = []
        for i, m in enumerate(body.messages):
            field = f"messages.{i}.content"
            if m.role in ("system", "developer"):
                system.append(_text_of(m.content, field))
            elif m.role == "assistant":
                turns.append(Turn.assistant(_text_of(m.content, field)))
            elif isinstance(m.content, str):
                turns.append(Turn.user(m.content))
            else:
                parts: list[Part] = []
                for j, p in enumerate(m.content):
                    if isinstance(p, _TextPart):
                        parts.append(p.text)
                    else:
                        parts.append(parse_data_url(p.image_url.url, f"{field}.{j}.image_url.url"))
                turns.append(Turn.user(*parts))
        if not turns or turns[-1].role != "user":
            raise RequestShapeError("messages", "the last message must be a user message")
        options = GenerationOptions(
            max_output_tokens=body.max_completion_tokens or body.max_tokens,
            temperature=body.temperature,
            reasoning_effort=body.reasoning_effort,
        )
        chat = ChatRequest(tuple(turns), "\n".join(system) or None, options)
        return IncomingRequest(api=self.name, model=body.model, chat=chat)

    def build_response(self, reply: ServerReply) -> dict[str, Any]:
        prompt, cached, written = openai_usage(reply.usage)
        message: dict[str, Any] = {"role": "assistant", "content": reply.text, "refusal": None}
        if reply.finish_reason == "refusal":
            message.update(content=None, refusal=reply.text)
        return {
            "id": f"chatcmpl-{uuid.uuid4().hex[:24]}",
            "object": "chat.completion",
            "created": int(time.time()),
            "model": reply.model,
            "choices": [
                {
                    "index": 0,
                    "message": message,
                    "logprobs": None,
                    "finish_reason": _openai_finish(reply.finish_reason),
                }
            ],
            "usage": {
                "prompt_tokens": prompt,
                "completion_tokens": reply.usage.output_tokens,
                "total_tokens": prompt + reply.usage.output_tokens,
                "prompt_tokens_details": {"cached_tokens": cached, "cache_write_tokens": written},
                "completion_tokens_details": {
                    "reasoning_tokens": reply.usage.reasoning_tokens or 0
                },
            },
        }

    def error_body(self, status: int, message: str) -> dict[str, Any]:
        error_type = openai_error_type(status)
        return {"error": {"message": message, "type": error_type, "param": None, "code": None}}

    def rate_limit_headers(self, states: Mapping[str, LimitState]) -> dict[str, str]:
        return openai_rate_limit_headers(states)
