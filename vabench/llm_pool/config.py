"""Endpoint configuration: one `ModelEndpoint` per model a sweep evaluates.

These pydantic models are the `models:` entries of a sweep YAML (the sweep issue reuses them
as they are). Every field has a default or is required for a reason, unknown keys are rejected
(a typo must not silently fall back to a default), and `load_endpoints` turns validation
failures into one `ConfigError` whose message names the field, e.g.
`models[1].limits.rpm: Input should be greater than 0`.

Which APIs exist, their default hosts and which generation options each accepts are the
registered adapters' (`apis.ADAPTERS`): `ApiName` is derived from that registry, and an
endpoint asks its API's adapter to check its options. The sections that no API decides
(`GenerationOptions`, `Limits`, `Prices`, `RetryPolicy`, `ConfigError`) live in `settings.py`,
below the adapters, and are importable from here too.

API keys never live in config: `api_key_env` names the environment variable that holds one.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any, Literal

from pydantic import Field, ValidationError, model_validator

from vabench.field_errors import dotted, plain_message
from vabench.llm_pool.apis import ApiName, get_adapter
from vabench.llm_pool.settings import (
    ConfigError,
    GenerationOptions,
    Limits,
    Prices,
    RetryPolicy,
    Strict,
)


class ModelEndpoint(Strict):
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
    prices: Prices | None = None
    """US dollars per million tokens; unset: costs show as "price not set" (`spend.Pricing`),
    and `limits.max_cost_usd` is refused."""
    generation: GenerationOptions = Field(default_factory=GenerationOptions)
    context_window: int = Field(default=262_144, ge=1024)
    """Tokens the model's context holds (prompt and output); the episode's conversation is
    compacted to fit it (`agent.conversation.ContextLimits`). Set it to the server's
    `max_model_len` / `num_ctx` for a model served with a smaller window."""
    retry: RetryPolicy = Field(default_factory=RetryPolicy)

    @model_validator(mode="after")
    def _options_fit_api(self) -> ModelEndpoint:
        get_adapter(self.api).check_options(self.generation)
        if self.base_url is not None and not self.base_url.startswith(("http://", "https://")):
            raise ConfigError("base_url", f"must start with http:// or https://: {self.base_url!r}")
        return self

    @property
    def provider_model(self) -> str:
        return self.model or self.name

    @property
    def resolved_base_url(self) -> str:
        return (self.base_url or get_adapter(self.api).default_base_url).rstrip("/")


def _as_config_error(err: ValidationError, prefix: str) -> ConfigError:
    """The first problem of an endpoint loaded on its own, worded as the sweep's config words
    it (`field_errors.plain_message`: "must be at least 1, got 0")."""
    first = err.errors()[0]
    ctx_error = first.get("ctx", {}).get("error")
    if isinstance(ctx_error, ConfigError):  # raised inside a validator: keep its field
        return ConfigError(dotted(ctx_error.field.split("."), prefix), ctx_error.message)
    return ConfigError(dotted(first["loc"], prefix), plain_message(first))


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
