"""The contract every provider API module fulfils, on both sides of the wire.

An `ApiAdapter` knows one API's shapes: the client half builds request bodies and parses
responses; the server half (used by the embedded server) validates request bodies against the
documented shape and writes responses and errors the way the provider does. Keeping both
halves of one API in one module is what lets the tests check that what the client sends is
what the API documents: the server parses it with the strict models written from the docs.
"""

from __future__ import annotations

import json
import math
import uuid
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from typing import Any, ClassVar, TypeVar

import pydantic_core
from pydantic import BaseModel, ValidationError

from vabench.llm_pool.config import ApiName, GenerationOptions, ModelEndpoint
from vabench.llm_pool.errors import ResponseFormatError
from vabench.llm_pool.messages import ChatRequest, FinishReason, Image, ParsedResponse, Usage

M = TypeVar("M", bound=BaseModel)
DATA_URL_MEDIA_TYPES = ("image/jpeg", "image/png", "image/gif", "image/webp")


class RequestShapeError(ValueError):
    """A request body that the API would reject; `field` is its dotted path."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}" if field else message)
        self.field = field
        self.message = message


@dataclass(frozen=True)
class IncomingRequest:
    """A request as the embedded server received it, in API-neutral form: what policies see.

    `cache_breakpoints` are indexes into `chat.blocks` after which the client asked
    for a cache entry (Anthropic cache_control markers); empty for OpenAI, which caches
    prefixes automatically.
    """

    api: ApiName
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


@dataclass(frozen=True)
class LimitState:
    """One rate limit as the server reports it in headers."""

    limit: int
    remaining: int
    reset_s: float


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
    at error.message), or the start of the body."""
    try:
        body = json.loads(raw)
        message = body["error"]["message"]
        if isinstance(message, str):
            return message[:limit]
    except (ValueError, KeyError, TypeError):
        pass
    return raw[:limit].decode("utf-8", "replace")


def go_duration(seconds: float) -> str:
    """Seconds as OpenAI writes them in reset headers: `20ms`, `1.5s`, `6m0s`."""
    if seconds < 1:
        return f"{max(0, math.ceil(seconds * 1000))}ms"
    minutes, secs = divmod(seconds, 60)
    secs_text = f"{secs:.3f}".rstrip("0").rstrip(".")
    return f"{int(minutes)}m{secs_text}s" if minutes else f"{secs_text}s"


def rfc3339_in(seconds: float) -> str:
    when = datetime.now(timezone.utc) + timedelta(seconds=seconds)
    return when.isoformat(timespec="milliseconds").replace("+00:00", "Z")


class ApiAdapter(ABC):
    """One provider API. Subclasses are stateless singletons registered in `apis.ADAPTERS`."""

    name: ClassVar[ApiName]
    route: ClassVar[str]
    """The path the embedded server serves, e.g. `/v1/chat/completions`."""

    @abstractmethod
    def image_tokens(self, width: int, height: int) -> int:
        """Estimated tokens of one image of this size under this API's rule."""

    # -- client half -------------------------------------------------------------------------
    @abstractmethod
    def url(self, base_url: str) -> str:
        """The endpoint URL for a configured base URL (see `ModelEndpoint.base_url`)."""

    @abstractmethod
    def headers(self, api_key: str | None) -> dict[str, str]:
        """Authentication and versioning headers."""

    @abstractmethod
    def build_body(
        self, endpoint: ModelEndpoint, request: ChatRequest, options: GenerationOptions
    ) -> dict[str, Any]:
        """The JSON body for one call."""

    @abstractmethod
    def parse_response(self, raw: bytes) -> ParsedResponse:
        """Read a 2xx body; raises `ResponseFormatError` naming the problem."""

    # -- server half -------------------------------------------------------------------------
    @abstractmethod
    def parse_request(self, raw: bytes, headers: Mapping[str, str]) -> IncomingRequest:
        """Validate a request as the API would; raises `RequestShapeError` naming the field."""

    @abstractmethod
    def build_response(self, reply: ServerReply) -> dict[str, Any]:
        """A success body in this API's shape, usage counted this API's way."""

    @abstractmethod
    def error_body(self, status: int, message: str) -> dict[str, Any]:
        """An error body in this API's shape."""

    @abstractmethod
    def rate_limit_headers(self, states: Mapping[str, LimitState]) -> dict[str, str]:
        """Rate-limit headers for `states` keyed by "requests" and "tokens"."""

    def server_key(self, headers: Mapping[str, str]) -> str | None:
        """The API key a request carries (for the server's optional key check)."""
        auth = headers.get("authorization", "")
        return auth[7:] if auth.lower().startswith("bearer ") else None

    def response_headers(self) -> dict[str, str]:
        """Headers the provider puts on every response (its request id)."""
        return {"x-request-id": request_id("req_")}


def openai_error_type(status: int) -> str:
    return {
        400: "invalid_request_error",
        401: "invalid_api_key",
        403: "permission_denied",
        404: "not_found",
        429: "rate_limit_exceeded",
    }.get(status, "server_error")


def openai_rate_limit_headers(states: Mapping[str, LimitState]) -> dict[str, str]:
    headers: dict[str, str] = {}
    for name, s in states.items():
        headers[f"x-ratelimit-limit-{name}"] = str(s.limit)
        headers[f"x-ratelimit-remaining-{name}"] = str(max(0, s.remaining))
        headers[f"x-ratelimit-reset-{name}"] = go_duration(s.reset_s)
    return headers


def openai_usage(usage: Usage) -> tuple[int, int, int]:
    """(prompt tokens including cached and written, cached, written): OpenAI counts cache
    reads and writes inside the prompt tokens and reports each in the prompt details."""
    return usage.prompt_tokens, usage.cached_input_tokens, usage.cache_write_tokens


def usage_from_openai(
    prompt_tokens: int,
    cached: int | None,
    output: int,
    reasoning: int | None,
    cache_write: int | None = None,
) -> Usage:
    cached, cache_write = cached or 0, cache_write or 0
    return Usage(
        input_tokens=max(0, prompt_tokens - cached - cache_write),
        cached_input_tokens=cached,
        cache_write_tokens=cache_write,
        output_tokens=output,
        reasoning_tokens=reasoning,
    )


def request_id(prefix: str) -> str:
    """A request id as providers send them in a response header (`request-id`, Anthropic;
    `x-request-id`, OpenAI), for a client to quote."""
    return f"{prefix}{uuid.uuid4().hex[:24]}"
