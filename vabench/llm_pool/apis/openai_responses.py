"""OpenAI Responses (`POST {base}/responses`).

Request: the system prompt is `instructions`; `input` is a list of messages whose user content
is `{"type":"input_text"}` and `{"type":"input_image","image_url":"data:...","detail":"auto"}`
parts (the image URL is a plain string here, not an object as in Chat Completions); assistant
turns are plain strings. `max_output_tokens`, `reasoning: {"effort": ...}`; `store: false`
so that no conversation state is kept on the provider's side (vabench resends the history).

Response: `output` is a list of items; the answer is the `output_text` parts of `message`
items, reasoning items carry optional summaries. `status` is `completed` or `incomplete`
(with `incomplete_details.reason`, e.g. `max_output_tokens`). Usage: `input_tokens` *includes*
`input_tokens_details.cached_tokens`; `output_tokens` includes
`output_tokens_details.reasoning_tokens`.
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
from vabench.llm_pool.errors import ResponseFormatError
from vabench.llm_pool.messages import (
    ChatRequest,
    FinishReason,
    ParsedResponse,
    Part,
    Turn,
    Usage,
)
from vabench.llm_pool.tokens import openai_image_tokens

# -- request shape ----------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class _InputText(_Strict):
    type: Literal["input_text"]
    text: str


class _InputImage(_Strict):
    type: Literal["input_image"]
    image_url: str
    detail: Literal["auto", "low", "high"] = "auto"


class _OutputText(_Strict):
    type: Literal["output_text"]
    text: str
    annotations: list[Any] = Field(default_factory=list)


_InputPart = Annotated[_InputText | _InputImage, Field(discriminator="type")]


class _UserMessage(_Strict):
    type: Literal["message"] | None = None
    role: Literal["user", "system", "developer"]
    content: str | list[_InputPart]


class _AssistantMessage(_Strict):
    type: Literal["message"] | None = None
    role: Literal["assistant"]
    content: str | list[_OutputText]


class _Reasoning(_Strict):
    effort: ReasoningEffort | None = None
    summary: Literal["auto", "concise", "detailed"] | None = None


class _TextFormat(_Strict):
    type: Literal["text", "json_object", "json_schema"]
    name: str | None = None
    schema_: dict[str, Any] | None = Field(default=None, alias="schema")
    strict: bool | None = None
    description: str | None = None


class _Text(_Strict):
    format: _TextFormat | None = None
    verbosity: Literal["low", "medium", "high"] | None = None


class ResponsesRequest(_Strict):
    """What the embedded server takes: the parameters a text-and-image call uses (no tools,
    background runs, stored conversations or streaming: vabench sends none of them)."""

    model: str = Field(min_length=1)
    input: str | list[_UserMessage | _AssistantMessage]
    instructions: str | None = None
    max_output_tokens: int | None = Field(default=None, ge=1)
    temperature: float | None = Field(default=None, ge=0, le=2)
    top_p: float | None = Field(default=None, ge=0, le=1)
    reasoning: _Reasoning | None = None
    text: _Text | None = None
    store: bool | None = None
    stream: Literal[False] | None = None
    user: str | None = None
    metadata: dict[str, str] | None = None
    prompt_cache_key: str | None = None
    service_tier: str | None = None
    truncation: Literal["auto", "disabled"] | None = None
    parallel_tool_calls: bool | None = None


# -- response shape ---------------------------------------------------------------------------


class _Loose(BaseModel):
    model_config = ConfigDict(extra="ignore")


class _Content(_Loose):
    type: str
    text: str | None = None
    refusal: str | None = None


class _Summary(_Loose):
    text: str = ""


class _OutputItem(_Loose):
    type: str
    content: list[_Content] | None = None
    summary: list[_Summary] | None = None


class _InputDetails(_Loose):
    cached_tokens: int | None = None
    cache_write_tokens: int | None = None


class _OutputDetails(_Loose):
    reasoning_tokens: int | None = None


class _Usage(_Loose):
    input_tokens: int
    output_tokens: int
    input_tokens_details: _InputDetails | None = None
    output_tokens_details: _OutputDetails | None = None


class _Incomplete(_Loose):
    reason: str | None = None


class _Error(_Loose):
    code: str | None = None
    message: str | None = None


class ResponsesResponse(_Loose):
    id: str | None = None
    model: str | None = None
    status: str | None = None
    output: list[_OutputItem]
    incomplete_details: _Incomplete | None = None
    error: _Error | None = None
    usage: _Usage | None = None


_INCOMPLETE: dict[str, FinishReason] = {
    "max_output_tokens": "length",
    "content_filter": "content_filter",
}


def _part(part: Part) -> dict[str, Any]:
    if isinstance(part, str):
        return {"type": "input_text", "text": part}
    return {"type": "input_image", "image_url": InlineImage(part, data_url=True), "detail": "auto"}


def _finish_of(body: ResponsesResponse, refused: bool) -> tuple[FinishReason, str | None]:
    if refused:
        return "refusal", body.status
    if body.status == "incomplete":
        reason = body.incomplete_details.reason if body.incomplete_details else None
        return _INCOMPLETE.get(reason or "", "other"), reason
    if body.status in (None, "completed"):
        return "stop", body.status
    return "other", body.status


class OpenAIResponses(ApiAdapter):
    name = "openai_responses"
    route = "/v1/responses"

    def image_tokens(self, width: int, height: int) -> int:
        return openai_image_tokens(width, height)

    def url(self, base_url: str) -> str:
        return f"{base_url}/responses"

    def headers(self, api_key: str | None) -> dict[str, str]:
        return {"Authorization": f"Bearer {api_key}"} if api_key else {}

    def build_body(
        self, endpoint: ModelEndpoint, request: ChatRequest, options: GenerationOptions
    ) -> dict[str, Any]:
        items: list[dict[str, Any]] = []
        for turn in request.turns:
            if turn.role == "assistant":
                items.append({"role": "assistant", "content": turn.text})
            else:
                items.append({"role": "user", "content": [_part(p) for p in turn.content]})
        body: dict[str, Any] = {
            "model": endpoint.provider_model,
            "input": items,
            "max_output_tokens": options.resolved_max_output_tokens,
            "store": False,
        }
        if request.system:
            body["instructions"] = request.system
        if options.temperature is not None:
            body["temperature"] = options.temperature
        if options.reasoning_effort is not None:
            body["reasoning"] = {"effort": options.reasoning_effort}
        return body

    def parse_response(self, raw: bytes) -> ParsedResponse:
        body = validate_response_json(ResponsesResponse, raw, "responses")
        if body.status == "failed":
            error = body.error or _Error()
            raise ResponseFormatError(
                f"responses: status 'failed' ({error.code}): {error.message or 'no message'}"
            )
        texts: list[str] = []
        summaries: list[str] = []
        refused = False
        for item in body.output:
            if item.type == "message":
                for c in item.content or []:
                    if c.type == "output_text" and c.text is not None:
                        texts.append(c.text)
                    elif c.type == "refusal":
                        refused = True
                        texts.append(c.refusal or "")
            elif item.type == "reasoning":
                summaries.extend(s.text for s in item.summary or [])
        finish, raw_finish = _finish_of(body, refused)
        u = body.usage
        usage = Usage()
        if u is not None:
            details = u.input_tokens_details or _InputDetails()
            usage = usage_from_openai(
                u.input_tokens,
                details.cached_tokens,
                u.output_tokens,
                u.output_tokens_details.reasoning_tokens if u.output_tokens_details else None,
                details.cache_write_tokens,
            )
        return ParsedResponse(
            text="".join(texts),
            finish_reason=finish,
            raw_finish_reason=raw_finish,
            usage=usage,
            model=body.model,
            response_id=body.id,
            reasoning="\n".join(summaries) or None,
            usage_reported=u is not None,
        )

    def parse_request(self, raw: bytes, headers: Mapping[str, str]) -> IncomingRequest:
        body = validate_request_json(ResponsesRequest, raw)
        system = [body.instructions] if body.instructions else []
        turns: list[Turn] = []
        items = (
            [_UserMessage(role="user", content=body.input)]
            if isinstance(body.input, str)
            else body.input
        )
        for i, item in enumerate(items):
            field = f"input.{i}.content"
            if isinstance(item, _AssistantMessage):
                text = (
                    item.content
                    if isinstance(item.content, str)
                    else "".join(c.text for c in item.content)
                )
                turns.append(Turn.assistant(text))
                continue
            parts: list[Part] = []
            if isinstance(item.content, str):
                parts.append(item.content)
            else:
                for j, p in enumerate(item.content):
                    if isinstance(p, _InputText):
                        parts.append(p.text)
                    else:
                        parts.append(parse_data_url(p.image_url, f"{field}.{j}.image_url"))
            if item.role == "user":
                turns.append(Turn.user(*parts))
            elif all(isinstance(p, str) for p in parts):
                system.append("\n".join(p for p in parts if isinstance(p, str)))
            else:
                raise RequestShapeError(field, "images are not allowed in system messages")
        if not turns or turns[-1].role != "user":
            raise RequestShapeError("input", "the last input message must be a user message")
        options = GenerationOptions(
            max_output_tokens=body.max_output_tokens,
            temperature=body.temperature,
            reasoning_effort=body.reasoning.effort if body.reasoning else None,
        )
        chat = ChatRequest(tuple(turns), "\n".join(system) or None, options)
        return IncomingRequest(api=self.name, model=body.model, chat=chat)

    def build_response(self, reply: ServerReply) -> dict[str, Any]:
        prompt, cached, written = openai_usage(reply.usage)
        output: list[dict[str, Any]] = []
        if reply.usage.reasoning_tokens:
            summary = [{"type": "summary_text", "text": reply.reasoning}] if reply.reasoning else []
            output.append({"type": "reasoning", "id": f"rs_{uuid.uuid4().hex}", "summary": summary})
        content = (
            {"type": "refusal", "refusal": reply.text}
            if reply.finish_reason == "refusal"
            else {"type": "output_text", "text": reply.text, "annotations": []}
        )
        output.append(
            {
                "type": "message",
                "id": f"msg_{uuid.uuid4().hex}",
                "status": "completed",
                "role": "assistant",
                "content": [content],
            }
        )
        incomplete = reply.finish_reason in ("length", "content_filter")
        reason = "max_output_tokens" if reply.finish_reason == "length" else "content_filter"
        return {
            "id": f"resp_{uuid.uuid4().hex}",
            "object": "response",
            "created_at": int(time.time()),
            "status": "incomplete" if incomplete else "completed",
            "incomplete_details": {"reason": reason} if incomplete else None,
            "error": None,
            "model": reply.model,
            "output": output,
            # what the Response object always carries (the SDK's strict types require them)
            "parallel_tool_calls": True,
            "tool_choice": "auto",
            "tools": [],
            "usage": {
                "input_tokens": prompt,
                "input_tokens_details": {"cached_tokens": cached, "cache_write_tokens": written},
                "output_tokens": reply.usage.output_tokens,
                "output_tokens_details": {"reasoning_tokens": reply.usage.reasoning_tokens or 0},
                "total_tokens": prompt + reply.usage.output_tokens,
            },
        }

    def error_body(self, status: int, message: str) -> dict[str, Any]:
        error_type = openai_error_type(status)
        return {"error": {"message": message, "type": error_type, "param": None, "code": None}}

    def rate_limit_headers(self, states: Mapping[str, LimitState]) -> dict[str, str]:
        return openai_rate_limit_headers(states)
