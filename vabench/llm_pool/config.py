"""Endpoint configuration: one `ModelEndpoint` per model a sweep evaluates.

These pydantic models are the `models:` entries of a sweep YAML (the sweep issue reuses them
as they are). Every field has a default or is required for a reason, unknown keys are rejected
(a typo must not silently fall back to a default), and `load_endpoints` turns validation
failures into one `ConfigError` whose message names the field, e.g.
`models[1].limits.rpm: Input should be greater than 0`.

API keys never live in config: `api_key_env` names the environment variable that holds one.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from vabench.field_errors import dotted

ApiName = Literal["openai_chat", "openai_responses", "anthropic"]
ReasoningEffort = Literal["none", "minimal", "low", "medium", "high"]

DEFAULT_MAX_OUTPUT_TOKENS = 4096  # the reference harness's max_tokens for every API
DEFAULT_BASE_URLS: dict[str, str] = {
    "openai_chat": "https://api.openai.com/v1",
    "openai_responses": "https://api.openai.com/v1",
    "anthropic": "https://api.anthropic.com",
}


class ConfigError(ValueError):
    """A configuration value that cannot be used; `field` is its dotted path."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}" if field else message)
        self.field = field
        self.message = message


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Limits(_Strict):
    """How hard vabench may drive one endpoint; shared by every episode using it."""

    max_concurrency: int = Field(default=64, ge=1)
    """Most requests in flight at once (also the size of the connection pool)."""
    rpm: float | None = Field(default=None, gt=0)
    """Requests per `period_s` (a minute by default); unset means unlimited."""
    tpm: float | None = Field(default=None, gt=0)
    """Tokens per `period_s`, counted as estimated input + max output tokens at admission and
    corrected to the reported usage afterwards (the way OpenAI and Anthropic count)."""
    adaptive: bool = False
    """Shrink the concurrency on 429/529 responses and grow it back on successes."""
    min_concurrency: int = Field(default=1, ge=1)
    """Floor for adaptive concurrency."""
    burst_s: float = Field(default=1.0, gt=0)
    """The rate limiters admit at most this many seconds' worth of rate at once, so traffic
    stays smooth for endpoints that enforce per-second slices of a per-minute limit."""
    period_s: float = Field(default=60.0, gt=0)
    """Length of the rate window. Providers use a minute; tests and the simulated server use
    shorter windows to exercise the same code quickly."""

    @model_validator(mode="after")
    def _floor_below_ceiling(self) -> Limits:
        if self.min_concurrency > self.max_concurrency:
            raise ValueError("min_concurrency must not exceed max_concurrency")
        return self


class Prices(_Strict):
    """US dollars per million tokens. Unset cached/cache-write prices fall back to `input`."""

    input: float = Field(default=0.0, ge=0)
    cached_input: float | None = Field(default=None, ge=0)
    cache_write: float | None = Field(default=None, ge=0)
    output: float = Field(default=0.0, ge=0)
    """Output price; reasoning tokens are billed as output by every provider."""


class GenerationOptions(_Strict):
    """Generation settings. Every field is optional: unset means "inherit" (a request's options
    override its endpoint's, which override the defaults of `resolved`)."""

    max_output_tokens: int | None = Field(default=None, ge=1)
    temperature: float | None = Field(default=None, ge=0, le=2)
    reasoning_effort: ReasoningEffort | None = None
    """OpenAI reasoning models only (Chat Completions and Responses)."""
    thinking_budget: int | None = Field(default=None, ge=1024)
    """Anthropic extended thinking; must be below max_output_tokens."""
    cache_prompt: bool | None = None
    """Anthropic: put cache_control markers on the stable prefix (default on). OpenAI caches
    prefixes automatically and ignores this."""

    def merge(self, override: GenerationOptions | None) -> GenerationOptions:
        """These options with every field that `override` sets replaced."""
        if override is None:
            return self
        return self.model_copy(update=override.model_dump(exclude_none=True))

    @property
    def resolved_max_output_tokens(self) -> int:
        return self.max_output_tokens or DEFAULT_MAX_OUTPUT_TOKENS


def check_options_for_api(api: ApiName, options: GenerationOptions) -> None:
    """Reject option combinations the API would answer with a 400, naming the field."""
    if api == "anthropic":
        if options.temperature is not None:
            raise ConfigError(
                "generation.temperature",
                "the Anthropic Messages API (version 2026-10-21, the official SDK's) takes no "
                "temperature; remove it (it applies to the OpenAI APIs only)",
            )
        if options.reasoning_effort is not None:
            raise ConfigError(
                "generation.reasoning_effort", "OpenAI only; use thinking_budget for anthropic"
            )
        budget = options.thinking_budget
        if budget is not None and budget >= options.resolved_max_output_tokens:
            raise ConfigError(
                "generation.thinking_budget",
                f"must be below max_output_tokens ({options.resolved_max_output_tokens})",
            )
    elif options.thinking_budget is not None:
        raise ConfigError(
            "generation.thinking_budget", "anthropic only; use reasoning_effort for OpenAI"
        )


class RetryPolicy(_Strict):
    """When and how long to retry one call."""

    max_attempts: int = Field(default=6, ge=1)
    """Attempts per call, the first included (the reference harness used 6)."""
    total_timeout_s: float = Field(default=900.0, gt=0)
    """Ceiling on one call from its first admission to its outcome, retries included."""
    request_timeout_s: float = Field(default=180.0, gt=0)
    """Ceiling on one attempt (connect, send, wait, read)."""
    backoff_base_s: float = Field(default=1.0, gt=0)
    """First backoff when the server gives no hint; doubles per attempt, with jitter."""
    backoff_max_s: float = Field(default=60.0, gt=0)


class ModelEndpoint(_Strict):
    """One model behind one API endpoint, as named in a sweep's `models:` list."""

    name: str = Field(min_length=1)
    """The label records and reports use; unique within a sweep."""
    api: ApiName
    model: str | None = None
    """The provider's model id; defaults to `name`."""
    base_url: str | None = None
    """OpenAI APIs: up to and including `/v1` (e.g. `http://localhost:8000/v1` for vLLM).
    Anthropic: the host (`https://api.anthropic.com`); a trailing `/v1` is accepted too."""
    api_key_env: str | None = None
    """Environment variable holding the key; unset for servers without authentication."""
    headers: dict[str, str] = Field(default_factory=dict)
    """Extra non-secret headers (e.g. OpenAI-Project)."""
    max_tokens_field: Literal["max_completion_tokens", "max_tokens"] = "max_completion_tokens"
    """Chat Completions: which field carries the output limit. OpenAI reasoning models require
    max_completion_tokens; some OpenAI-compatible servers (Ollama) only read max_tokens."""
    limits: Limits = Field(default_factory=Limits)
    prices: Prices = Field(default_factory=Prices)
    generation: GenerationOptions = Field(default_factory=GenerationOptions)
    retry: RetryPolicy = Field(default_factory=RetryPolicy)

    @model_validator(mode="after")
    def _options_fit_api(self) -> ModelEndpoint:
        check_options_for_api(self.api, self.generation)
        if self.base_url is not None and not self.base_url.startswith(("http://", "https://")):
            raise ConfigError("base_url", f"must start with http:// or https://: {self.base_url!r}")
        return self

    @property
    def provider_model(self) -> str:
        return self.model or self.name

    @property
    def resolved_base_url(self) -> str:
        return (self.base_url or DEFAULT_BASE_URLS[self.api]).rstrip("/")


def _as_config_error(err: ValidationError, prefix: str) -> ConfigError:
    first = err.errors()[0]
    message = first["msg"]
    ctx_error = first.get("ctx", {}).get("error")
    if isinstance(ctx_error, ConfigError):  # raised inside a validator: keep its field
        return ConfigError(dotted(ctx_error.field.split("."), prefix), ctx_error.message)
    message = message.removeprefix("Value error, ")
    return ConfigError(dotted(first["loc"], prefix), message)


def load_endpoint(data: Mapping[str, Any], *, where: str = "") -> ModelEndpoint:
    """Validate one endpoint mapping; errors name the field, prefixed by `where`."""
    try:
        return ModelEndpoint.model_validate(data)
    except ValidationError as err:
        raise _as_config_error(err, where) from None


def load_endpoints(
    data: Iterable[Mapping[str, Any] | ModelEndpoint], *, where: str = "models"
) -> list[ModelEndpoint]:
    """Validate a `models:` list: each entry, then that names are unique."""
    endpoints: list[ModelEndpoint] = []
    for i, entry in enumerate(data):
        if isinstance(entry, ModelEndpoint):
            endpoints.append(entry)
        elif isinstance(entry, Mapping):
            endpoints.append(load_endpoint(entry, where=f"{where}[{i}]"))
        else:
            raise ConfigError(f"{where}[{i}]", f"expected a mapping, got {type(entry).__name__}")
    seen: set[str] = set()
    for i, ep in enumerate(endpoints):
        if ep.name in seen:
            raise ConfigError(f"{where}[{i}].name", f"duplicate endpoint name {ep.name!r}")
        seen.add(ep.name)
    return endpoints
