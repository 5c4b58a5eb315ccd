"""The embedded server's settings: which policy answers which model (and in how many worker
processes the stateless ones compute their replies), in how many processes it serves, and what
it simulates around the policy: latency, faults, rate limits, an API key, prompt caching, the
request log, and the limits of a local inference server (`ServerTraits`: vLLM's image and
context limits, Ollama's silent truncation, llama.cpp's unread output-limit field).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator

from vabench.children import usable_cores
from vabench.llm_pool.faults import FaultConfig
from vabench.llm_pool.policies import PURE_REPLIES
from vabench.llm_pool.simulate import LatencyModel


class PolicySpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    policy: str
    options: dict[str, Any] = Field(default_factory=dict)


def policy_workers(setting: int | str, cores: int | None = None) -> int:
    """The policy worker processes of `ServerConfig.policy_processes` on `cores` (default: this
    process's, `children.usable_cores`: a sweep worker's share of the host)."""
    if setting != "auto":
        return int(setting)
    cores = usable_cores() if cores is None else cores
    return cores // 2 if cores >= 4 else 0


class ServerTraits(BaseModel):
    """Limits of a local inference server, answered as that server answers them, so that
    `vabench.check` can be tested against each (every field unset: no such limit)."""

    model_config = ConfigDict(extra="forbid")
    served_model_name: str | None = None
    """vLLM's `--served-model-name`: `/v1/models` lists this model alone, and a request for
    another name gets vLLM's 404 "The model `NAME` does not exist."."""
    max_model_len: int | None = Field(default=None, ge=1)
    """vLLM's `--max-model-len`: `/v1/models` says it (`max_model_len`), and a request whose
    prompt and output limit exceed it gets vLLM's context-length 400."""
    max_images_per_prompt: int | None = Field(default=None, ge=0)
    """vLLM's `--limit-mm-per-prompt` image count (older releases default to 1): a request with
    more images gets vLLM's 400 "At most N image(s) may be provided in one request."."""
    num_ctx: int | None = Field(default=None, ge=1)
    """Ollama's context (2,048 or 4,096 tokens unless set): a longer prompt is cut to this many
    tokens without an error, and the usage reports the cut prompt."""
    ignored_fields: list[Literal["max_completion_tokens", "max_tokens"]] = Field(
        default_factory=list
    )
    """Output-limit fields the server does not read (llama.cpp's server read only `max_tokens`
    and `n_predict` until it took `max_completion_tokens`): the reply runs to its end."""
    reasoning_model: bool = False
    """An OpenAI reasoning model's parameter rules: `max_tokens` refused (it takes
    `max_completion_tokens` only), a `temperature` other than 1 refused, in OpenAI's words."""
    no_reasoning: bool = False
    """A model that does not reason (OpenAI's gpt-4o, say): `reasoning_effort` refused, in
    OpenAI's words."""


class ServerConfig(BaseModel):
    """Everything the embedded server simulates; every field has a harmless default."""

    model_config = ConfigDict(extra="forbid")
    policy: str = "random_action"
    policy_options: dict[str, Any] = Field(default_factory=dict)
    model_policies: dict[str, PolicySpec] = Field(default_factory=dict)
    """Policy per requested model name; other names get `policy`."""
    latency: LatencyModel = Field(default_factory=LatencyModel)
    faults: FaultConfig = Field(default_factory=FaultConfig)
    rpm: float | None = Field(default=None, gt=0)
    tpm: float | None = Field(default=None, gt=0)
    rate_period_s: float = Field(default=60.0, gt=0)
    retry_after_header: bool = True
    """Send Retry-After with enforced 429s; False leaves only the API's reset headers."""
    api_key: SecretStr | None = None
    """Require this key (Bearer; the Anthropic route also takes it as x-api-key)."""
    simulate_cache: bool = True
    log_path: str | None = None
    """Append one JSON line per request here."""
    log_size: int = Field(default=10_000, ge=0)
    """Requests kept in memory (`LocalServer.log`)."""
    seed: int | None = None
    imitate: ServerTraits = Field(default_factory=ServerTraits)
    """The limits of a local inference server to answer as it does (tests of the check)."""
    policy_processes: int | Literal["auto"] = 0
    """Worker processes that compute the replies of stateless policies (`policies.PURE_REPLIES`:
    reference_servo, conversation_hash), so a CPU-heavy policy uses several cores while this
    process keeps the HTTP, the simulated latency, caching, limits and faults. 0: replies are
    computed here, in a thread. "auto": half the cores from 4 cores on (the other half runs the
    sweep's own processes), else 0 (`policy_workers`). Other policies ignore it."""

    server_processes: int | Literal["auto"] = 0
    """Processes that serve the API routes on one port (SO_REUSEPORT: the kernel spreads the
    connections over them). 0: the server runs in the caller's event loop. n >= 1: the caller
    does no HTTP work at all; its `LocalServer` starts n processes, each answering in its own
    threads, and collects their request records (`log`, `counts`, `log_path`). Each process has
    its own policy state, simulated prompt cache, fault plan and latency draws (seeded from
    `seed` and its index), so rate limits (`rpm`, `tpm`), which must see every request, need 0.
    "auto": half the cores (`children.usable_cores`) from 4 cores on when every policy is
    stateless (`policies.PURE_REPLIES`) and no rate limit is set, else 0
    (`serving_processes`)."""

    @field_validator("policy_processes", "server_processes", mode="plain")
    @classmethod
    def _processes(cls, value: Any) -> int | Literal["auto"]:
        whole = isinstance(value, int) and not isinstance(value, bool)
        if value == "auto" or (whole and value >= 0):
            return value
        raise ValueError(f"expected 'auto' or a whole number >= 0, got {value!r}")

    @model_validator(mode="after")
    def _limits_in_one_process(self) -> ServerConfig:
        if isinstance(self.server_processes, int) and self.server_processes > 0:
            limits = [name for name in ("rpm", "tpm") if getattr(self, name) is not None]
            if limits:
                verb = "is" if len(limits) == 1 else "are"
                raise ValueError(
                    f"server_processes: {' and '.join(limits)} {verb} enforced by one process, "
                    "which must see every request; set server_processes: 0"
                )
        return self

    @property
    def policies(self) -> tuple[str, ...]:
        """Every policy that answers some model."""
        return (self.policy, *(spec.policy for spec in self.model_policies.values()))


def serving_processes(config: ServerConfig, cores: int | None = None) -> int:
    """How many processes serve `config` on `cores` (default: this process's)
    (`ServerConfig.server_processes`; 0: in the caller's event loop)."""
    if config.server_processes != "auto":
        return config.server_processes
    cores = usable_cores() if cores is None else cores
    stateless = all(name in PURE_REPLIES for name in config.policies)
    limited = config.rpm is not None or config.tpm is not None
    return cores // 2 if cores >= 4 and stateless and not limited else 0


def serving_description(config: ServerConfig, cores: int) -> str:
    """Where a server of `config` started by a process of `cores` cores does its work."""
    served = serving_processes(config, cores)
    if served:
        return f"{served} processes on one port, each computing its replies"
    workers = policy_workers(config.policy_processes, cores)
    stateless = any(name in PURE_REPLIES for name in config.policies)
    if workers and stateless:
        return f"in the engine's process, the replies in {workers} policy worker processes"
    return "in the engine's process"
