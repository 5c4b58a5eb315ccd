"""OpenAI Responses (`POST {base}/responses`).

Request: the system prompt is `instructions`; `input` is a list of messages whose user content
is `{"type":"input_text"}` and `{"type":"input_image","image_url":"data:...","detail":"auto"}`
parts (the image URL is a plain string here, not an object as in Chat Completions); assistant
turns are plain strings. `max_output_tokens`, `reasoning: {"effort": ...}`; `store: false`
so that no conversation state is kept on the provider's side (vabench resends the history).

Response: `output` is a list of items; the answer is the `output_text` parts of `message`
items joined (a `refusal` part makes the reply a refusal), reasoning items carry optional
summaries and, from open-weight servers (vLLM's gpt-oss), `reasoning_text` content: both go
to the reasoning; `function_call` items are function calls. `status` is `completed` or `incomplete`
(with `incomplete_details.reason`, e.g. `max_output_tokens`). Usage: `input_tokens` *includes*
`input_tokens_details.cached_tokens`; `output_tokens` includes
`output_tokens_details.reasoning_tokens`.
"""

from __future__ import annotations

import time
import uuid
from typing import Annotated, Any, Literal

from pydantic import Field

from vabench.llm_pool.apis import base
from vabench.llm_pool.apis import openai_common as common
from vabench.llm_pool.errors import ResponseFormatError
from vabench.llm_pool.messages import ChatRequest, FinishReason, FunctionCall, Part, Turn, Usage
from vabench.llm_pool.settings import GenerationOptions, ReasoningEffort

# -- request shape ----------------------------------------------------------------------------


class _InputText(base.ContentPart):
    type: Literal["input_text"]
    text: str

    def part(self, field: str) -> Part:
        return self.text


class _InputImage(base.ContentPart):
    type: Literal["input_image"]
    image_url: str
    detail: Literal["auto", "low", "high"] = "auto"

    def part(self, field: str) -> Part:
        return base.parse_data_url(self.image_url, f"{field}.image_url")


class _OutputText(base.StrictModel):
    type: Literal["output_text"]
    text: str
    annotations: list[Any] = Field(default_factory=list)


_InputPart = Annotated[_InputText | _InputImage, Field(discriminator="type")]


class _UserMessage(base.StrictModel):
    type: Literal["message"] | None = None
    role: Literal["user", "system", "developer"]
    content: str | list[_InputPart]


class _AssistantMessage(base.StrictModel):
    type: Literal["message"] | None = None
    role: Literal["assistant"]
    content: str | list[_OutputText]

    @property
    def text(self) -> str:
        return (
            self.content if isinstance(self.content, str) else "".join(c.text for c in self.content)
        )


class _Reasoning(base.StrictModel):
    effort: ReasoningEffort | None = None
    summary: Literal["auto", "concise", "detailed"] | None = None


class _TextFormat(base.StrictModel):
    type: Literal["text", "json_object", "json_schema"]
    name: str | None = None
    schema_: dict[str, Any] | None = Field(default=None, alias="schema")
    strict: bool | None = None
    description: str | None = None


class _Text(base.StrictModel):
    format: _TextFormat | None = None
    verbosity: Literal["low", "medium", "high"] | None = None


class ResponsesRequest(base.RequestBody):
    """What the embedded server takes: the parameters a text-and-image call uses (no tools,
    background runs, stored conversations or streaming: vabench sends none of them)."""

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


class _Content(base.LooseModel):
    type: str
    text: str | None = None
    refusal: str | None = None


class _Summary(base.LooseModel):
    text: str = ""


class _OutputItem(base.LooseModel):
    type: str
    content: list[_Content] | None = None
    summary: list[_Summary] | None = None
    name: str | None = None
    arguments: str | None = None


class _Usage(base.UsageBody):
    input_tokens: int
    output_tokens: int
    input_tokens_details: common.PromptDetails | None = None
    output_tokens_details: common.OutputDetails | None = None

    def to_usage(self) -> Usage:
        return common.usage_of(
            self.input_tokens,
            self.input_tokens_details,
            self.output_tokens,
            self.output_tokens_details,
        )


class _Incomplete(base.LooseModel):
    reason: str | None = None


class _Error(base.LooseModel):
    code: str | None = None
    message: str | None = None


class ResponsesResponse(base.ResponseBody):
    status: str | None = None
    output: list[_OutputItem]
    incomplete_details: _Incomplete | None = None
    error: _Error | None = None
    usage: _Usage | None = None


_INCOMPLETE: dict[str, FinishReason] = {
    "max_output_tokens": "length",
    "content_filter": "content_filter",
}


def _finish_of(body: ResponsesResponse, refused: bool) -> tuple[FinishReason, str | None]:
    if refused:
        return "refusal", body.status
    if body.status == "incomplete":
        reason = body.incomplete_details.reason if body.incomplete_details else None
        return _INCOMPLETE.get(reason or "", "other"), reason
    if body.status in (None, "completed"):
        return "stop", body.status
    return "other", body.status


class OpenAIResponses(common.OpenAIApi[ResponsesRequest, ResponsesResponse]):
    name = "openai_responses"
    route = "/v1/responses"
    request_model = ResponsesRequest
    response_model = ResponsesResponse
    response_label = "responses"
    last_turn_error = ("input", "the last input message must be a user message")

    def build_body(
        self, endpoint: base.Endpoint, request: ChatRequest, options: GenerationOptions
    ) -> dict[str, Any]:
        body: dict[str, Any] = {
            "model": endpoint.provider_model,
            "input": self.messages(request),
            "max_output_tokens": options.resolved_max_output_tokens,
            "store": False,
        }
        if request.system:
            body["instructions"] = request.system
        if options.temperature is not None:
            body["temperature"] = options.temperature
        if options.sent_reasoning_effort is not None:
            body["reasoning"] = {"effort": options.sent_reasoning_effort}
        return body

    def part(self, part: Part) -> dict[str, Any]:
        if isinstance(part, str):
            return {"type": "input_text", "text": part}
        image_url = base.InlineImage(part, data_url=True)
        return {"type": "input_image", "image_url": image_url, "detail": "auto"}

    def read_answer(self, body: ResponsesResponse) -> base.Answer:
        if body.status == "failed":
            error = body.error or _Error()
            raise ResponseFormatError(
                f"responses: status 'failed' ({error.code}): {error.message or 'no message'}"
            )
        texts: list[str] = []
        summaries: list[str] = []
        calls: list[FunctionCall] = []
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
                summaries.extend(c.text or "" for c in item.content or [])
            elif item.type == "function_call":
                calls.append(FunctionCall(item.name or "", item.arguments or ""))
        finish, raw_finish = _finish_of(body, refused)
        return base.Answer(
            text="".join(texts),
            finish_reason=finish,
            raw_finish_reason=raw_finish,
            usage=body.usage,
            reasoning=base.join_reasoning(*summaries),
            function_calls=tuple(calls),
        )

    def read_request(self, body: ResponsesRequest) -> base.Prompt:
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
                turns.append(Turn.assistant(item.text))
                continue
            parts = base.parts_of(item.content, field)
            if item.role == "user":
                turns.append(Turn.user(*parts))
            elif all(isinstance(p, str) for p in parts):
                system.append("\n".join(p for p in parts if isinstance(p, str)))
            else:
                raise base.RequestShapeError(field, "images are not allowed in system messages")
        options = GenerationOptions(
            max_output_tokens=body.max_output_tokens,
            temperature=body.temperature,
            reasoning_effort=body.reasoning.effort if body.reasoning else None,
        )
        return base.Prompt(turns, "\n".join(system) or None, options)

    def build_response(self, reply: base.ServerReply) -> dict[str, Any]:
        u = reply.usage
        output: list[dict[str, Any]] = []
        if u.reasoning_tokens:
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
                "input_tokens": u.prompt_tokens,
                "input_tokens_details": common.prompt_details(u),
                "output_tokens": u.output_tokens,
                "output_tokens_details": common.output_details(u),
                "total_tokens": u.total_tokens,
            },
        }
