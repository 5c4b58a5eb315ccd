"""The contract every provider API module fulfils, on both sides of the wire, and the steps
the APIs share.

An `ApiAdapter` is everything vabench knows about one API, and its registration in
`apis.ADAPTERS` is the only place an API is named: its config name, where its endpoints are
(default host, base URL path), which generation options it takes (`check_options`), its image
token rule (the pool's TPM estimate, the server's usage and the dry-run's cost estimate all
use it), the client half that builds request bodies and parses responses, and the server half
(used by the embedded server) that serves its route, validates request bodies against the
documented shape, writes responses and errors the way the provider does, and says how the
provider caches prompts. Keeping both halves of one API in one module is what lets the tests
check that what the client sends is what the API documents: the server parses it with the
strict models written from the docs.

The steps are written once, here: turns into messages, a 2xx body into a `ParsedResponse`, a
request body into an `IncomingRequest`, rate-limit and request-id headers. An API module
supplies only what its API does differently: its request and response models, how a content
part, an answer and a usage block read, and its header names. Beside the contract are the
helpers those steps use: validation errors that name the field, inline images from data URLs,
images spliced into encoded bodies, a provider's error message.
"""

from __future__ import annotations

import json
import uuid
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, Literal, Protocol, TypeVar

import pydantic_core
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from vabench.llm_pool.errors import ResponseFormatError
from vabench.llm_pool.messages import (
    ChatRequest,
    FinishReason,
    FunctionCall,
    Image,
    ParsedResponse,
    Part,
    Turn,
    Usage,
)
from vabench.llm_pool.settings import GenerationOptions
from vabench.protocol.extract import split_reasoning

M = TypeVar("M", bound=BaseModel)
DATA_URL_MEDIA_TYPES = ("image/jpeg", "image/png", "image/gif", "image/webp")
PromptCaching = Literal["automatic", "explicit"]
"""How a provider caches prompt prefixes, which the embedded server simulates
(`simulate.PromptCache`): "automatic" (OpenAI: every prefix ending at a turn boundary) or
"explicit" (Anthropic: only prefixes ending at a client's cache_control marker)."""


class RequestShapeError(ValueError):
    """A request body that the API would reject; `field` is its dotted path."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}" if field else message)
        self.field = field
        self.message = message


class Endpoint(Protocol):
    """What a request body needs of the endpoint it goes to: a `config.ModelEndpoint` is one.

    A structural type, so that the adapters need not import `config.py`, which sits above
    their registry (it derives `ApiName` from `apis.ADAPTERS`): else the two would import each
    other."""

    @property
    def provider_model(self) -> str:
        """The provider's model id."""
        ...

    @property
    def max_tokens_field(self) -> str:
        """Chat Completions: the field that carries the output limit."""
        ...


@dataclass(frozen=True)
class IncomingRequest:
    """A request as the embedded server received it, in API-neutral form: what policies see.

    `cache_breakpoints` are indexes into `chat.blocks` after which the client asked
    for a cache entry (Anthropic cache_control markers); empty for OpenAI, which caches
    prefixes automatically.
    """

    api: str
    """The registered name of the API it came through (`ApiAdapter.name`)."""
    model: str
    chat: ChatRequest
    cache_breakpoints: tuple[int, ...] = ()


@dataclass(frozen=True)
class ServerReply:
    """What the embedded server answers, before an adapter puts it in its API's shape."""

    text: str
    finish_reason: FinishReason
    usage: Usage
    model: str
    reasoning: str | None = None
    body: dict[str, Any] | None = None
    """A success body sent verbatim instead of the API's own shape: a scripted policy's way to
    answer as a particular server writes its replies (`PolicyReply.body`)."""


@dataclass(frozen=True)
class LimitState:
    """One rate limit as the server reports it in headers."""

    limit: int
    remaining: int
    reset_s: float


@dataclass(frozen=True)
class Prompt:
    """A request body read into API-neutral parts, before the checks every API makes."""

    turns: list[Turn]
    system: str | None
    options: GenerationOptions
    cache_breakpoints: tuple[int, ...] = ()


class StrictModel(BaseModel):
    """A request shape as the API documents it: an unknown field is an error."""

    model_config = ConfigDict(extra="forbid")


class LooseModel(BaseModel):
    """A response shape: unknown fields are ignored (APIs add them), required ones checked."""

    model_config = ConfigDict(extra="ignore")


class RequestBody(StrictModel):
    """The field every API's request body starts with."""

    model: str = Field(min_length=1)


class ContentPart(StrictModel):
    """One part of a message's content in a request body; reads itself into a `Part`."""

    @abstractmethod
    def part(self, field: str) -> Part:
        """The part; `field` names it in a `RequestShapeError` (an image that does not read)."""


def parts_of(content: str | Sequence[ContentPart], field: str) -> list[Part]:
    """A message's content as parts: a plain string is one text part; a list of parts is
    read part by part, each naming its own field (`{field}.{index}`)."""
    if isinstance(content, str):
        return [content]
    return [p.part(f"{field}.{j}") for j, p in enumerate(content)]


class UsageBody(LooseModel):
    """The usage block of a response, counted the API's way."""

    @abstractmethod
    def to_usage(self) -> Usage:
        """The counts split our way (see `Usage`)."""


class ResponseBody(LooseModel):
    """The fields every API's response body starts with."""

    id: str | None = None
    model: str | None = None


@dataclass(frozen=True)
class Answer:
    """An API's reading of a 2xx body: its answer and its usage block (None when absent)."""

    text: str
    finish_reason: FinishReason
    raw_finish_reason: str | None
    usage: UsageBody | None
    reasoning: str | None = None
    function_calls: tuple[FunctionCall, ...] = ()


def join_reasoning(*parts: str | None) -> str | None:
    """Reasoning texts of one reply, joined; None when there is none."""
    text = "\n".join(p.strip() for p in parts if p and p.strip())
    return text or None


_TYPE_LABELS = frozenset({"str", "int", "float", "bool", "list", "dict", "none"})


def _loc(loc: Sequence[Any]) -> str:
    """A field path without the labels pydantic adds for union branches (`str`, `list[...]`,
    `_UserMessage`); discriminator tags ("image_url") stay, they say which kind of part."""
    return ".".join(
        str(p)
        for p in loc
        if not (
            isinstance(p, str)
            and ("[" in p or p.startswith("_") or p[:1].isupper() or p in _TYPE_LABELS)
        )
    )


def _most_specific(err: ValidationError) -> Any:
    """Of a union's failed branches, the error that got deepest into the value."""
    return max(err.errors(include_url=False), key=lambda e: len(e["loc"]))


def validate_request_json(model: type[M], raw: bytes | str) -> M:
    """Parse and validate a request body; errors become `RequestShapeError(field, ...)`."""
    try:
        return model.model_validate_json(raw)
    except ValidationError as err:
        e = _most_specific(err)
        if e["type"] == "json_invalid":
            raise RequestShapeError("", f"body is not valid JSON: {e['msg']}") from None
        raise RequestShapeError(_loc(e["loc"]), e["msg"]) from None


def validate_response_json(model: type[M], raw: bytes, api: str) -> M:
    """Parse and validate a response body; errors become `ResponseFormatError` naming the
    problem (the JSON position, or the missing/wrong field)."""
    if not raw.strip():
        raise ResponseFormatError(f"{api} response: empty body")
    try:
        return model.model_validate_json(raw)
    except ValidationError as err:
        e = _most_specific(err)
        if e["type"] == "json_invalid":
            raise ResponseFormatError(f"{api} response: invalid JSON: {e['msg']}") from None
        raise ResponseFormatError(f"{api} response: field '{_loc(e['loc'])}': {e['msg']}") from None


def parse_data_url(url: str, field: str) -> Image:
    """An inline image from a `data:<media type>;base64,<data>` URL, without decoding it."""
    if not url.startswith("data:"):
        raise RequestShapeError(
            field, "only inline base64 data URLs are supported (the local server has no network)"
        )
    header, sep, data = url.partition(",")
    media_type = header[5:].removesuffix(";base64")
    if not sep or not header.endswith(";base64"):
        raise RequestShapeError(field, "data URL must be of the form data:<type>;base64,<data>")
    return base64_image(data, media_type, field)


def base64_image(data: str, media_type: str, field: str) -> Image:
    if media_type not in DATA_URL_MEDIA_TYPES:
        raise RequestShapeError(field, f"unsupported image type {media_type!r}")
    if not data or len(data) % 4:
        raise RequestShapeError(field, "image data is not valid base64 (length)")
    image = Image(b64=data, media_type=media_type)  # type: ignore[arg-type]
    try:
        image.head(64)
    except ValueError as err:
        raise RequestShapeError(field, f"image data is not valid base64: {err}") from None
    return image


class InlineImage:
    """An image's base64 inside a request body, spliced into the encoded JSON by
    `encode_body` instead of going through the JSON encoder (which would scan and copy the
    half-megabyte of base64 a call carries: ~1 ms per call, the client's largest cost)."""

    __slots__ = ("image", "prefix")

    def __init__(self, image: Image, *, data_url: bool):
        self.image = image
        self.prefix = image.data_url_prefix.encode("ascii") if data_url else b""

    def text(self) -> str:
        return self.prefix.decode("ascii") + self.image.b64


_MARK = "\x1fvabench-inline-image\x1f"
_MARK_JSON = b"\\u001fvabench-inline-image\\u001f"  # how the JSON encoder writes _MARK


def _unsupported(obj: Any) -> Any:
    raise TypeError(f"cannot encode {type(obj).__name__} in a request body")


def encode_body(payload: Any) -> bytes:
    """A request body as JSON bytes, with every `InlineImage` spliced in place."""
    images: list[InlineImage] = []

    def mark(obj: Any) -> Any:
        if isinstance(obj, InlineImage):
            images.append(obj)
            return _MARK
        return _unsupported(obj)

    raw = pydantic_core.to_json(payload, fallback=mark)
    pieces = raw.split(_MARK_JSON)
    if len(pieces) != len(images) + 1:  # the marker occurs in the text itself: encode plainly
        return pydantic_core.to_json(
            payload, fallback=lambda o: o.text() if isinstance(o, InlineImage) else _unsupported(o)
        )
    out = [pieces[0]]
    for image, piece in zip(images, pieces[1:], strict=True):
        out += [image.prefix, image.image.b64_ascii, piece]
    return b"".join(out)


def error_message(raw: bytes, limit: int = 500) -> str:
    """The provider's error message from an error body (both OpenAI's and Anthropic's put it
    at error.message; a gateway's may be multi-line), or the start of the body: one line,
    whatever the body."""
    text = raw[: limit * 4].decode("utf-8", "replace")
    try:
        body = json.loads(raw)
        message = body["error"]["message"]
        if isinstance(message, str):
            text = message
    except (ValueError, KeyError, TypeError):
        pass
    line = " ".join(text.split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def error_words(raw: bytes) -> str:
    """Everything an error body says about its cause, on one line: its message, and its
    error's type and code where it has them (`auth_error`, `model_not_found`)."""
    words = [error_message(raw, 2000)]
    try:
        error = json.loads(raw)["error"]
        words += [str(error.get(k)) for k in ("type", "code") if error.get(k) is not None]
    except (ValueError, KeyError, TypeError, AttributeError):
        pass
    return " ".join(words)


def request_id(prefix: str) -> str:
    """A request id as providers send them in a response header (`request-id`, Anthropic;
    `x-request-id`, OpenAI), for a client to quote."""
    return f"{prefix}{uuid.uuid4().hex[:24]}"


RequestT = TypeVar("RequestT", bound=RequestBody)
ResponseT = TypeVar("ResponseT", bound=ResponseBody)


class ApiAdapter(ABC, Generic[RequestT, ResponseT]):
    """One provider API. Subclasses are stateless singletons registered in `apis.ADAPTERS`,
    the one list of the APIs there are (see the module docstring for what that registration
    decides).

    The steps every API shares are written here once; a subclass supplies its shapes (the
    request and response models), the way its parts and answers read, and its header names.
    """

    name: ClassVar[str]
    """The name a config's `api:` field gives (`config.ApiName` is the registry's names)."""
    route: ClassVar[str]
    """The path the embedded server serves, e.g. `/v1/chat/completions`."""
    default_host: ClassVar[str]
    """Where an endpoint without a `base_url` goes, e.g. `https://api.openai.com`."""
    base_path: ClassVar[str]
    """The part of `route` that a configured base URL includes (`ModelEndpoint.base_url`):
    `/v1` for OpenAI (`https://api.openai.com/v1`), nothing for Anthropic (the host)."""
    prompt_caching: ClassVar[PromptCaching]
    """How the provider caches prompt prefixes (the embedded server simulates it)."""
    request_model: type[RequestT]
    """The request shape as documented (the embedded server validates against it)."""
    response_model: type[ResponseT]
    """The response shape (lenient: unknown fields are ignored, required ones are checked)."""
    response_label: ClassVar[str]
    """How errors about this API's response bodies name it."""
    last_turn_error: ClassVar[tuple[str, str]] = (
        "messages",
        "the last message must be a user message",
    )
    rate_limit_header: ClassVar[str]
    """Rate-limit header names, with `{limit}` (requests, tokens) and `{field}` (limit,
    remaining, reset)."""
    request_id_header: ClassVar[str] = "x-request-id"
    reasoning_option: ClassVar[str] = "reasoning_effort"
    """The generation option that asks this API's models to reason (`reasoning_effort` or
    `thinking_budget`): the protocol's default is set through it (`agent.generation`)."""
    output_field_choice: ClassVar[bool] = False
    """Whether servers of this API differ in the output limit's field
    (`ModelEndpoint.max_tokens_field`), so that a refusal or a probe should name it."""

    @abstractmethod
    def image_tokens(self, width: int, height: int) -> int:
        """Estimated tokens of one image of this size under this API's rule."""

    @abstractmethod
    def check_options(self, options: GenerationOptions) -> None:
        """Reject option combinations this API would answer with a 400: a `ConfigError`
        naming the field (`generation.<option>`)."""

    def base_url_for(self, host: str) -> str:
        """The `base_url` an endpoint of this API gives to reach the API at `host` (a provider,
        or the embedded server's `http://127.0.0.1:<port>`)."""
        return host + self.base_path

    @property
    def default_base_url(self) -> str:
        return self.base_url_for(self.default_host)

    # -- client half -------------------------------------------------------------------------
    @abstractmethod
    def url(self, base_url: str) -> str:
        """The endpoint URL for a configured base URL (see `ModelEndpoint.base_url`)."""

    def headers(self, api_key: str | None) -> dict[str, str]:
        """Authentication and versioning headers: the key as a bearer token."""
        return {"Authorization": f"Bearer {api_key}"} if api_key else {}

    @abstractmethod
    def build_body(
        self, endpoint: Endpoint, request: ChatRequest, options: GenerationOptions
    ) -> dict[str, Any]:
        """The JSON body for one call."""

    @abstractmethod
    def part(self, part: Part) -> dict[str, Any]:
        """One text or image part of a user turn in this API's shape."""

    def messages(self, request: ChatRequest) -> list[dict[str, Any]]:
        """The turns as every API takes them: an assistant turn's text as a plain string, a
        user turn's content as a list of parts."""
        return [
            {"role": "assistant", "content": turn.text}
            if turn.role == "assistant"
            else {"role": "user", "content": [self.part(p) for p in turn.content]}
            for turn in request.turns
        ]

    def parse_response(self, raw: bytes) -> ParsedResponse:
        """Read a 2xx body; raises `ResponseFormatError` naming the problem."""
        body = validate_response_json(self.response_model, raw, self.response_label)
        answer = self.read_answer(body)
        text, inline = split_reasoning(answer.text)
        return ParsedResponse(
            text=text,
            finish_reason=answer.finish_reason,
            raw_finish_reason=answer.raw_finish_reason,
            usage=answer.usage.to_usage() if answer.usage is not None else Usage(),
            model=body.model,
            response_id=body.id,
            reasoning=join_reasoning(answer.reasoning, inline),
            function_calls=answer.function_calls,
            usage_reported=answer.usage is not None,
        )

    @abstractmethod
    def read_answer(self, body: ResponseT) -> Answer:
        """The answer of a validated 2xx body: its text parts joined, its reasoning and
        function calls apart (`messages` module docstring); inline `<think>` blocks are split
        off by `parse_response`, for every API alike."""

    # -- server half -------------------------------------------------------------------------
    def parse_request(self, raw: bytes, headers: Mapping[str, str]) -> IncomingRequest:
        """Validate a request as the API would; raises `RequestShapeError` naming the field."""
        body = validate_request_json(self.request_model, raw)
        prompt = self.read_request(body)
        if not prompt.turns or prompt.turns[-1].role != "user":
            raise RequestShapeError(*self.last_turn_error)
        chat = ChatRequest(tuple(prompt.turns), prompt.system, prompt.options)
        return IncomingRequest(
            api=self.name, model=body.model, chat=chat, cache_breakpoints=prompt.cache_breakpoints
        )

    @abstractmethod
    def read_request(self, body: RequestT) -> Prompt:
        """The prompt of a validated request body; raises `RequestShapeError` for what the
        shape alone does not rule out."""

    @abstractmethod
    def build_response(self, reply: ServerReply) -> dict[str, Any]:
        """A success body in this API's shape, usage counted this API's way."""

    @abstractmethod
    def error_body(self, status: int, message: str) -> dict[str, Any]:
        """An error body in this API's shape."""

    def rate_limit_headers(self, states: Mapping[str, LimitState]) -> dict[str, str]:
        """Rate-limit headers for `states` keyed by "requests" and "tokens"."""
        headers: dict[str, str] = {}
        for limit, s in states.items():
            for field, value in (
                ("limit", str(s.limit)),
                ("remaining", str(max(0, s.remaining))),
                ("reset", self.reset_text(s.reset_s)),
            ):
                headers[self.rate_limit_header.format(limit=limit, field=field)] = value
        return headers

    @abstractmethod
    def reset_text(self, seconds: float) -> str:
        """A rate limit's reset, `seconds` from now, as this API writes it."""

    def server_key(self, headers: Mapping[str, str]) -> str | None:
        """The API key a request carries (for the server's optional key check)."""
        auth = headers.get("authorization", "")
        return auth[7:] if auth.lower().startswith("bearer ") else None

    def response_headers(self) -> dict[str, str]:
        """Headers the provider puts on every response (its request id)."""
        return {self.request_id_header: request_id("req_")}
