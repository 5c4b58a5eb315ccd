"""The sections of an endpoint's configuration that no model API decides: generation options,
limits, prices, the retry policy, and the error a bad value raises.

They sit below the API adapters (`apis/`), which read generation options out of request bodies
and check them (`ApiAdapter.check_options`); `config.py`, above the adapters, puts them
together with a registered API into a `ModelEndpoint` (the `models:` entries of a sweep).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

ReasoningEffort = Literal["none", "minimal", "low", "medium", "high"]
OFF = "off"
"""The value of a reasoning option that sends no such field at all (and so switches the
benchmark's default for it off, `vabench.agent.generation`): for a model or server that refuses
the field, or a comparison run without the default."""

DEFAULT_MAX_OUTPUT_TOKENS = 4096  # the reference harness's max_tokens for every API


class ConfigError(ValueError):
    """A configuration value that cannot be used; `field` is its dotted path."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}" if field else message)
        self.field = field
        self.message = message


class Strict(BaseModel):
    """A config section: an unknown key is an error (a typo must not fall back to a default)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class Limits(Strict):
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
    max_cost_usd: float | None = Field(default=None, gt=0)
    """US dollars this model may spend in one sweep (its run directory, resumes included): a
    call that could cross it is not sent (`spend.SpendCaps`). Needs `prices`."""

    @model_validator(mode="after")
    def _floor_below_ceiling(self) -> Limits:
        if self.min_concurrency > self.max_concurrency:
            raise ValueError("min_concurrency must not exceed max_concurrency")
        return self


class Prices(Strict):
    """US dollars per million tokens. Unset cached/cache-write prices fall back to `input`."""

    input: float = Field(default=0.0, ge=0)
    cached_input: float | None = Field(default=None, ge=0)
    cache_write: float | None = Field(default=None, ge=0)
    output: float = Field(default=0.0, ge=0)
    """Output price; reasoning tokens are billed as output by every provider."""


class GenerationOptions(Strict):
    """Generation settings. Every field is optional: unset means "inherit" (a request's options
    override its endpoint's, which override the defaults of `resolved`)."""

    max_output_tokens: int | None = Field(default=None, ge=1)
    temperature: float | None = Field(default=None, ge=0, le=2)
    reasoning_effort: ReasoningEffort | Literal["off"] | None = None
    """OpenAI reasoning models only (Chat Completions and Responses); `off`: the field is not
    sent (unset: the benchmark's default, `medium`)."""
    thinking_budget: Annotated[int, Field(ge=1024)] | Literal["off"] | None = None
    """Anthropic extended thinking; must be below max_output_tokens; `off`: no thinking
    (unset: the benchmark's default, 1,024 tokens)."""
    cache_prompt: bool | None = None
    """Anthropic: put cache_control markers on the stable prefix (default on). OpenAI caches
    prefixes automatically and ignores this."""

    @field_validator("reasoning_effort", "thinking_budget", mode="before")
    @classmethod
    def _yaml_off(cls, value: object) -> object:
        # YAML reads a bare `off` as false: the user wrote `off`
        return OFF if value is False else value

    def merge(self, override: GenerationOptions | None) -> GenerationOptions:
        """These options with every field that `override` sets replaced."""
        if override is None:
            return self
        return self.model_copy(update=override.model_dump(exclude_none=True))

    @property
    def sent_reasoning_effort(self) -> ReasoningEffort | None:
        """The `reasoning_effort` a request carries (None: no such field)."""
        effort = self.reasoning_effort
        return None if effort == "off" else effort

    @property
    def sent_thinking_budget(self) -> int | None:
        """The thinking budget a request carries (None: thinking not enabled)."""
        budget = self.thinking_budget
        return budget if isinstance(budget, int) else None

    @property
    def resolved_max_output_tokens(self) -> int:
        return self.max_output_tokens or DEFAULT_MAX_OUTPUT_TOKENS


class RetryPolicy(Strict):
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
