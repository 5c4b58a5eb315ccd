"""The embedded server's settings: which policy answers which model (and in how many worker
processes the stateless ones compute their replies), and what it simulates around the policy:
latency, faults, rate limits, an API key, prompt caching, the request log.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator

from vabench.children import usable_cores
from vabench.llm_pool.faults import FaultConfig
from vabench.llm_pool.simulate import LatencyModel


class PolicySpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    policy: str
    options: dict[str, Any] = Field(default_factory=dict)


def policy_workers(setting: int | str) -> int:
    """The policy worker processes of `ServerConfig.policy_processes` on this process's cores
    (`children.usable_cores`: a sweep worker's share of the host)."""
    if setting != "auto":
        return int(setting)
    cores = usable_cores()
    return cores // 2 if cores >= 4 else 0


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
    policy_processes: int | Literal["auto"] = 0
    """Worker processes that compute the replies of stateless policies (`policies.PURE_REPLIES`:
    reference_servo, conversation_hash), so a CPU-heavy policy uses several cores while this
    process keeps the HTTP, the simulated latency, caching, limits and faults. 0: replies are
    computed here, in a thread. "auto": half the cores from 4 cores on (the other half runs the
    sweep's own processes), else 0 (`policy_workers`). Other policies ignore it."""

    @field_validator("policy_processes", mode="plain")
    @classmethod
    def _policy_processes(cls, value: Any) -> int | Literal["auto"]:
        whole = isinstance(value, int) and not isinstance(value, bool)
        if value == "auto" or (whole and value >= 0):
            return value
        raise ValueError(f"expected 'auto' or a whole number >= 0, got {value!r}")
