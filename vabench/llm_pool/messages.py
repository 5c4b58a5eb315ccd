"""What goes into a call and what comes out, independent of the provider API.

A `ChatRequest` is a system prompt plus turns whose content is an ordered list of text and
images (order matters: a five-view bundle labels each image with the text before it). A
`CompletionResult` is the normalised answer: text, finish reason, usage, cost, timings.

Images keep their bytes and their base64 text side by side and compute the missing one once:
an episode resends its last few images on every call, so encoding them once per episode rather
than once per call matters at hundreds of calls per second. The embedded server creates images
from base64 and decodes them only if a policy asks for the bytes.
"""

from __future__ import annotations

import base64
import binascii
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

from vabench.llm_pool.settings import GenerationOptions, Prices

FinishReason = Literal["stop", "length", "content_filter", "refusal", "other"]
MediaType = Literal["image/jpeg", "image/png", "image/gif", "image/webp"]


class Image:
    """An image to send inline (JPEG by default).

    The base64 text is kept as ASCII bytes when this side encoded it (the request body is
    bytes, so it is spliced in without another copy) and as the received string on the
    server side; `b64` and `b64_ascii` give either form.
    """

    __slots__ = ("_b64", "_data", "media_type")

    def __init__(
        self,
        data: bytes | None = None,
        *,
        b64: str | bytes | None = None,
        media_type: MediaType = "image/jpeg",
    ):
        if (data is None) == (b64 is None):
            raise ValueError("Image needs exactly one of data (bytes) or b64 (base64 text)")
        self._data = data
        self._b64 = b64
        self.media_type = media_type

    @property
    def data(self) -> bytes:
        if self._data is None:
            try:
                self._data = base64.b64decode(self._b64 or b"", validate=True)
            except binascii.Error as err:
                raise ValueError(f"image is not valid base64: {err}") from None
        return self._data

    @property
    def b64_ascii(self) -> bytes:
        """The base64 encoding as ASCII bytes (computed once)."""
        if self._b64 is None:
            self._b64 = base64.b64encode(self._data or b"")
        return self._b64 if isinstance(self._b64, bytes) else self._b64.encode("ascii")

    @property
    def b64(self) -> str:
        b64 = self._b64 if self._b64 is not None else self.b64_ascii
        return b64 if isinstance(b64, str) else b64.decode("ascii")

    def head(self, n: int = 4096) -> bytes:
        """The first bytes (for reading the JPEG header) without decoding the whole image."""
        if self._data is not None:
            return self._data[:n]
        chunk = (self._b64 or b"")[: (n + 2) // 3 * 4]
        return base64.b64decode(chunk[: len(chunk) // 4 * 4])

    @property
    def data_url_prefix(self) -> str:
        return f"data:{self.media_type};base64,"

    @property
    def data_url(self) -> str:
        return self.data_url_prefix + self.b64

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Image):
            return NotImplemented
        if self.media_type != other.media_type:
            return False
        if self._b64 is not None and other._b64 is not None:
            return self.b64_ascii == other.b64_ascii
        return self.data == other.data

    __hash__ = None  # type: ignore[assignment]  # mutable cache; compare by content only

    def __repr__(self) -> str:
        size = len(self._data) if self._data is not None else len(self._b64 or b"") * 3 // 4
        return f"Image({self.media_type}, ~{size} bytes)"


Part = str | Image


@dataclass(frozen=True)
class Turn:
    """One message: a role and its ordered text and image parts."""

    role: Literal["user", "assistant"]
    content: tuple[Part, ...]

    def __post_init__(self) -> None:
        if self.role not in ("user", "assistant"):
            raise ValueError(f"turn role must be 'user' or 'assistant', got {self.role!r}")
        parts = tuple(self.content)
        if not parts:
            raise ValueError("a turn needs at least one text or image part")
        for i, part in enumerate(parts):
            if not isinstance(part, str | Image):
                raise TypeError(f"turn content[{i}]: expected str or Image, got {type(part)}")
        object.__setattr__(self, "content", parts)

    @classmethod
    def user(cls, *parts: Part) -> Turn:
        return cls("user", parts)

    @classmethod
    def assistant(cls, text: str) -> Turn:
        return cls("assistant", (text,))

    @property
    def text(self) -> str:
        return "\n".join(p for p in self.content if isinstance(p, str))

    @property
    def images(self) -> list[Image]:
        return [p for p in self.content if isinstance(p, Image)]


@dataclass(frozen=True)
class ChatRequest:
    """A system prompt, the conversation so far, and per-call option overrides."""

    turns: tuple[Turn, ...]
    system: str | None = None
    options: GenerationOptions | None = None
    """Overrides of the endpoint's generation options (a plain mapping is validated into
    `GenerationOptions`)."""

    def __post_init__(self) -> None:
        turns = tuple(self.turns)
        if not turns:
            raise ValueError("a ChatRequest needs at least one turn")
        if turns[-1].role != "user":
            raise ValueError("the last turn of a ChatRequest must be a user turn")
        object.__setattr__(self, "turns", turns)
        if isinstance(self.options, Mapping):  # a plain mapping is validated here, once
            object.__setattr__(self, "options", GenerationOptions.model_validate(self.options))

    @property
    def images(self) -> list[Image]:
        return [im for t in self.turns for im in t.images]

    @property
    def last_user_text(self) -> str:
        return self.turns[-1].text

    @property
    def blocks(self) -> list[Part]:
        """The prompt as a flat list: the system prompt (if any), then every turn's parts.
        Cache breakpoints and prefix token counts index into this list."""
        blocks: list[Part] = [self.system] if self.system else []
        for turn in self.turns:
            blocks.extend(turn.content)
        return blocks


def _add_optional(a: int | None, b: int | None) -> int | None:
    return None if a is None and b is None else (a or 0) + (b or 0)


@dataclass(frozen=True)
class Usage:
    """Token counts of one call, split so that the parts add up and each has one price.

    The APIs count differently: OpenAI's prompt/input tokens *include* the cached ones (and
    have no cache-write charge); Anthropic's input_tokens *exclude* both cache reads and cache
    writes, which it reports beside them. Here `input_tokens` is always the uncached,
    unwritten part, so input + cached_input + cache_write is the whole prompt everywhere.
    `output_tokens` includes reasoning; `reasoning_tokens` is the reasoning share of it, or
    None where the API does not report it (Anthropic bills thinking as output without a
    separate count).
    """

    input_tokens: int = 0
    cached_input_tokens: int = 0
    cache_write_tokens: int = 0
    output_tokens: int = 0
    reasoning_tokens: int | None = None

    @property
    def prompt_tokens(self) -> int:
        return self.input_tokens + self.cached_input_tokens + self.cache_write_tokens

    @property
    def total_tokens(self) -> int:
        return self.prompt_tokens + self.output_tokens

    def __add__(self, other: Usage) -> Usage:
        return Usage(
            self.input_tokens + other.input_tokens,
            self.cached_input_tokens + other.cached_input_tokens,
            self.cache_write_tokens + other.cache_write_tokens,
            self.output_tokens + other.output_tokens,
            _add_optional(self.reasoning_tokens, other.reasoning_tokens),
        )

    def cost(self, prices: Prices) -> float:
        """US dollars at `prices` (per million tokens)."""
        cached = prices.input if prices.cached_input is None else prices.cached_input
        write = prices.input if prices.cache_write is None else prices.cache_write
        return (
            self.input_tokens * prices.input
            + self.cached_input_tokens * cached
            + self.cache_write_tokens * write
            + self.output_tokens * prices.output
        ) / 1e6


@dataclass(frozen=True)
class FunctionCall:
    """A function call a model made although no tools were offered: the function's name and
    its arguments as the API gave them (JSON text, or an object for Anthropic's `tool_use`)."""

    name: str
    arguments: str | dict[str, object]


@dataclass(frozen=True)
class ParsedResponse:
    """What an API adapter reads from a successful response body."""

    text: str
    finish_reason: FinishReason
    raw_finish_reason: str | None
    usage: Usage
    model: str | None = None
    response_id: str | None = None
    reasoning: str | None = None
    """Reasoning text, kept apart from the answer (module docstring)."""
    function_calls: tuple[FunctionCall, ...] = ()
    usage_reported: bool = True
    """False when the body had no usage (local servers omit it at times): zero tokens."""


@dataclass(frozen=True)
class CompletionResult:
    """The normalised outcome of one successful call."""

    endpoint: str
    text: str
    finish_reason: FinishReason
    raw_finish_reason: str | None
    usage: Usage
    cost_usd: float
    latency_s: float
    """The successful attempt: request sent to response parsed."""
    elapsed_s: float
    """The whole call from its first admission: retries and backoff included."""
    attempts: int
    model: str | None = None
    response_id: str | None = None
    reasoning: str | None = None
    function_calls: tuple[FunctionCall, ...] = ()
    failures: tuple[str, ...] = field(default=())
    """One line per failed attempt before the success (status or error), for the record."""
