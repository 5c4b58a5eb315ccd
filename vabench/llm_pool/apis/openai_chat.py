"""OpenAI Chat Completions (`POST {base}/chat/completions`), and every OpenAI-compatible
server (vLLM, SGLang, Ollama, llama.cpp) through the same path.

Request: the system prompt is the first message (`role: system`); user content is a list of
`{"type":"text"}` and `{"type":"image_url","image_url":{"url":"data:image/jpeg;base64,..."}}`
parts; assistant turns are plain strings. The output limit goes in `max_completion_tokens`
(or `max_tokens`, see `ModelEndpoint.max_tokens_field`), `reasoning_effort` is top-level.

Response: `choices[0].message.content`, `finish_reason`; usage `prompt_tokens` *includes*
`prompt_tokens_details.cached_tokens`; `completion_tokens` includes
`completion_tokens_details.reasoning_tokens`. How real servers write the message, all read
here: `content` a string, null, or a list of parts (`{"type": "text", "text": ...}`, joined;
reasoning or thinking parts go to the reasoning); a reasoning model's thoughts in
`reasoning_content` (SGLang, older vLLM) or `reasoning` (vLLM since it renamed the field,
OpenRouter); a refusal in `refusal` (OpenAI, with finish_reason "stop"); function calls in
`tool_calls` or the legacy `function_call`; finish_reason "length" at the output limit.
"""

from __future__ import annotations

import time
import uuid
from typing import Annotated, Any, Literal

from pydantic import Field

from vabench.llm_pool.apis import base
from vabench.llm_pool.apis import openai_common as common
from vabench.llm_pool.messages import ChatRequest, FinishReason, FunctionCall, Part, Turn, Usage
from vabench.llm_pool.settings import GenerationOptions, ReasoningEffort

# -- request shape (as documented; the embedded server validates against it) ----------------


class _TextPart(base.ContentPart):
    type: Literal["text"]
    text: str

    def part(self, field: str) -> Part:
        return self.text


class _ImageURL(base.StrictModel):
    url: str
    detail: Literal["auto", "low", "high"] | None = None


class _ImagePart(base.ContentPart):
    type: Literal["image_url"]
    image_url: _ImageURL

    def part(self, field: str) -> Part:
        return base.parse_data_url(self.image_url.url, f"{field}.image_url.url")


_ContentPart = Annotated[_TextPart | _ImagePart, Field(discriminator="type")]


class _Message(base.StrictModel):
    role: Literal["system", "developer", "user", "assistant"]
    content: str | list[_ContentPart]
    name: str | None = None


class _ResponseFormat(base.StrictModel):
    type: Literal["text", "json_object", "json_schema"]
    json_schema: dict[str, Any] | None = None


class ChatCompletionsRequest(base.RequestBody):
    """What the embedded server takes: the parameters a text-and-image call uses (no tools,
    audio, logprobs or streaming: vabench sends none of them, and none is served)."""

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


class _Usage(base.UsageBody):
    prompt_tokens: int
    completion_tokens: int
    prompt_tokens_details: common.PromptDetails | None = None
    completion_tokens_details: common.OutputDetails | None = None

    def to_usage(self) -> Usage:
        return common.usage_of(
            self.prompt_tokens,
            self.prompt_tokens_details,
            self.completion_tokens,
            self.completion_tokens_details,
        )


class _Function(base.LooseModel):
    name: str = ""
    arguments: str | dict[str, Any] | None = None


class _ToolCall(base.LooseModel):
    function: _Function | None = None


class _AnswerMessage(base.LooseModel):
    content: str | list[Any] | None = None
    refusal: str | None = None
    reasoning_content: str | None = None
    reasoning: str | None = None
    tool_calls: list[_ToolCall] | None = None
    function_call: _Function | None = None

    def answer_and_reasoning(self) -> tuple[str, str | None]:
        """The text parts joined, and the reasoning (fields and reasoning parts)."""
        thoughts = [self.reasoning_content, self.reasoning]
        if isinstance(self.content, str) or self.content is None:
            return self.content or "", base.join_reasoning(*thoughts)
        texts: list[str] = []
        for part in self.content:
            if isinstance(part, str):
                texts.append(part)
            elif isinstance(part, dict):
                kind, text = part.get("type"), part.get("text")
                if kind in ("reasoning", "thinking"):
                    thoughts.append(text if isinstance(text, str) else part.get("thinking"))
                elif kind in ("text", "output_text", None) and isinstance(text, str):
                    texts.append(text)
        return "".join(texts), base.join_reasoning(*thoughts)

    def functions(self) -> tuple[FunctionCall, ...]:
        calls = [c.function for c in self.tool_calls or [] if c.function is not None]
        if self.function_call is not None:
            calls.append(self.function_call)
        return tuple(FunctionCall(f.name, f.arguments or "") for f in calls)


class _Choice(base.LooseModel):
    message: _AnswerMessage
    finish_reason: str | None = None


class ChatCompletionsResponse(base.ResponseBody):
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


def _text_of(content: str | list[_ContentPart], field: str) -> str:
    if isinstance(content, str):
        return content
    texts = []
    for i, p in enumerate(content):
        if not isinstance(p, _TextPart):
            raise base.RequestShapeError(f"{field}.{i}", "only text parts are allowed in this role")
        texts.append(p.text)
    return "\n".join(texts)


class OpenAIChat(common.OpenAIApi[ChatCompletionsRequest, ChatCompletionsResponse]):
    name = "openai_chat"
    output_field_choice = True  # max_completion_tokens or max_tokens (local servers)
    route = "/v1/chat/completions"
    request_model = ChatCompletionsRequest
    response_model = ChatCompletionsResponse
    response_label = "chat completions"

    def build_body(
        self, endpoint: base.Endpoint, request: ChatRequest, options: GenerationOptions
    ) -> dict[str, Any]:
        system = [{"role": "system", "content": request.system}] if request.system else []
        body: dict[str, Any] = {
            "model": endpoint.provider_model,
            "messages": system + self.messages(request),
            endpoint.max_tokens_field: options.resolved_max_output_tokens,
        }
        if options.temperature is not None:
            body["temperature"] = options.temperature
        if options.sent_reasoning_effort is not None:
            body["reasoning_effort"] = options.sent_reasoning_effort
        return body

    def part(self, part: Part) -> dict[str, Any]:
        if isinstance(part, str):
            return {"type": "text", "text": part}
        return {"type": "image_url", "image_url": {"url": base.InlineImage(part, data_url=True)}}

    def read_answer(self, body: ChatCompletionsResponse) -> base.Answer:
        choice = body.choices[0]
        message = choice.message
        finish: FinishReason = _FINISH.get(choice.finish_reason or "", "other")
        text, reasoning = message.answer_and_reasoning()
        if message.refusal:
            finish = "refusal"
            text = message.refusal
        return base.Answer(
            text=text,
            finish_reason=finish,
            raw_finish_reason=choice.finish_reason,
            usage=body.usage,
            reasoning=reasoning,
            function_calls=message.functions(),
        )

    def read_request(self, body: ChatCompletionsRequest) -> base.Prompt:
        if body.max_tokens is not None and body.max_completion_tokens is not None:
            raise base.RequestShapeError(
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
            else:
                turns.append(Turn.user(*base.parts_of(m.content, field)))
        options = GenerationOptions(
            max_output_tokens=body.max_completion_tokens or body.max_tokens,
            temperature=body.temperature,
            reasoning_effort=body.reasoning_effort,
        )
        return base.Prompt(turns, "\n".join(system) or None, options)

    def build_response(self, reply: base.ServerReply) -> dict[str, Any]:
        u = reply.usage
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
                "prompt_tokens": u.prompt_tokens,
                "completion_tokens": u.output_tokens,
                "total_tokens": u.total_tokens,
                "prompt_tokens_details": common.prompt_details(u),
                "completion_tokens_details": common.output_details(u),
            },
        }
