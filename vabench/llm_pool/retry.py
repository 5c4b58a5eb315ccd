"""Retry decisions as values, and how long the server asked us to wait.

`decide(status, headers)` says whether a response is retried and why; the pool turns the
decision into a wait with `backoff_delay`. The server's hint wins over our own backoff, read in
this order (the first present wins):

1. `retry-after-ms` (milliseconds; Azure OpenAI and OpenAI send it),
2. `Retry-After` (seconds, or an HTTP date),
3. the API's rate-limit reset headers for the limits that are exhausted: OpenAI
   `x-ratelimit-reset-{requests,tokens}` (Go durations such as `1s`, `6m0s`, `20ms`) and
   Anthropic `anthropic-ratelimit-{requests,tokens,input-tokens,output-tokens}-reset`
   (RFC 3339 timestamps). When no `remaining` header says which limit is exhausted, the
   latest reset is used.

A LiteLLM proxy relays its upstream's headers under an `llm_provider-` prefix (and sends its
own 429's wait as `llm_provider-retry-after`): when the headers above say nothing, the same
headers under that prefix are read in the same order.
"""

from __future__ import annotations

import random
import re
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from email.utils import parsedate_to_datetime
from typing import Literal

from vabench.llm_pool.config import RetryPolicy

ErrorMeaning = Literal["key", "model", "upstream"]
"""What an error body says beyond its status: the key was refused (`key`), the model name is
unknown (`model`), or a gateway could not reach its upstream (`upstream`)."""

_KEY = re.compile(
    r"api[ _-]?key|\bauth(?:entication|orization|_error)?\b|unauthori[sz]ed|credential|"
    r"no connected db|invalid[ _-]?(?:x-)?key|permission[ _-]denied|\bforbidden\b",
    re.IGNORECASE,
)
_MODEL = re.compile(
    r"model_not_found|no such model|unknown model|invalid model|"
    r"model\b[^.\n]{0,80}\b(?:not found|does not exist|not exist|unknown|is not supported|"
    r"not available|invalid)",
    re.IGNORECASE,
)
# Not LiteLLM's "No fallback was attempted": it ends every error the proxy relays, an upstream's
# own 500 and its rate limits included.
_UPSTREAM = re.compile(
    r"connection error|apiconnectionerror|connecterror|connection refused|cannot connect|"
    r"failed to connect|upstream connect error|"
    r"name or service not known|connection reset",
    re.IGNORECASE,
)

RETRYABLE_STATUSES = frozenset({408, 409, 429})
OVERLOAD_STATUSES = frozenset({429, 529})  # the endpoint says "less, please": adapt to it
MAX_HINT_S = 3600.0  # ignore absurd hints (a clock far off, a daily quota) beyond an hour


@dataclass(frozen=True)
class RetryDecision:
    """`no`: fail now. `transient`: back off and retry. `rate_limit`: the endpoint is over its
    limits or overloaded; wait at least `retry_after` seconds when the server said so."""

    kind: Literal["no", "transient", "rate_limit"]
    reason: str
    retry_after: float | None = None

    @property
    def retry(self) -> bool:
        return self.kind != "no"


def decide(status: int, headers: Mapping[str, str], *, now: float | None = None) -> RetryDecision:
    """Classify a non-2xx response. `headers` must be case-insensitive (aiohttp's are)."""
    hint = server_retry_after(headers, now=now)
    if status in OVERLOAD_STATUSES:
        return RetryDecision("rate_limit", f"HTTP {status}", hint)
    if status in RETRYABLE_STATUSES or status >= 500:
        return RetryDecision("transient", f"HTTP {status}", hint)
    return RetryDecision("no", f"HTTP {status}")


def meaning_of(status: int, message: str) -> ErrorMeaning | None:
    """What an error reply's `message` (its body's error message, type and code) says, read
    the same for a provider and for a gateway relaying it: a gateway answers a wrong key with
    a 400 ("No connected db."), a missing one with a 500, a down upstream with a 500 naming
    the connection error. None when it says none of these (the status decides)."""
    if status < 400:
        return None
    if _UPSTREAM.search(message) and status >= 500:
        return "upstream"
    if _MODEL.search(message):
        return "model"
    if _KEY.search(message):
        return "key"
    return None


_GO_DURATION = re.compile(r"(\d+(?:\.\d+)?)(ms|us|µs|ns|h|m|s)")
_GO_UNITS = {"h": 3600.0, "m": 60.0, "s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9}


def parse_go_duration(text: str) -> float | None:
    """Seconds in an OpenAI reset header (`1s`, `6m0s`, `20ms`, `1h2m3.5s`); None if not one."""
    text = text.strip()
    if not text:
        return None
    pos, total = 0, 0.0
    for match in _GO_DURATION.finditer(text):
        if match.start() != pos:
            return None
        total += float(match.group(1)) * _GO_UNITS[match.group(2)]
        pos = match.end()
    if pos != len(text):
        try:  # some gateways send bare seconds
            return float(text)
        except ValueError:
            return None
    return total


def _seconds_until(timestamp: str, now: float) -> float | None:
    """Seconds from `now` (epoch) to an RFC 3339 or HTTP-date timestamp."""
    text = timestamp.strip()
    try:
        when = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        try:
            when = parsedate_to_datetime(text)
        except (TypeError, ValueError):
            return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=timezone.utc)
    return when.timestamp() - now


def _plausible(seconds: float | None) -> float | None:
    if seconds is None or seconds != seconds:  # NaN
        return None
    return min(max(seconds, 0.0), MAX_HINT_S)


def _retry_after(headers: Mapping[str, str], now: float) -> float | None:
    ms = headers.get("retry-after-ms")
    if ms is not None:
        try:
            return _plausible(float(ms) / 1000.0)
        except ValueError:
            pass
    value = headers.get("retry-after")
    if value is not None:
        try:
            return _plausible(float(value))
        except ValueError:
            return _plausible(_seconds_until(value, now))
    return None


_OPENAI_LIMITS = ("requests", "tokens")
_ANTHROPIC_LIMITS = ("requests", "tokens", "input-tokens", "output-tokens")


def _reset_hint(headers: Mapping[str, str], now: float) -> float | None:
    """Seconds until the exhausted rate limits reset, from either provider's headers."""
    resets: list[tuple[bool, float]] = []  # (known exhausted, seconds)
    for limit in _OPENAI_LIMITS:
        reset = headers.get(f"x-ratelimit-reset-{limit}")
        seconds = parse_go_duration(reset) if reset is not None else None
        if seconds is not None:
            resets.append((headers.get(f"x-ratelimit-remaining-{limit}") == "0", seconds))
    for limit in _ANTHROPIC_LIMITS:
        reset = headers.get(f"anthropic-ratelimit-{limit}-reset")
        seconds = _seconds_until(reset, now) if reset is not None else None
        if seconds is not None:
            resets.append((headers.get(f"anthropic-ratelimit-{limit}-remaining") == "0", seconds))
    if not resets:
        return None
    exhausted = [s for known, s in resets if known]
    return _plausible(max(exhausted or [s for _, s in resets]))


RELAYED_PREFIX = "llm_provider-"
"""How a LiteLLM proxy names the upstream's headers it relays (and its own 429's wait)."""


def server_retry_after(headers: Mapping[str, str], *, now: float | None = None) -> float | None:
    """How long the server asked us to wait, in seconds, or None if it did not say; a
    gateway's relayed hint (`RELAYED_PREFIX`) when the server's own headers say nothing."""
    now = datetime.now(timezone.utc).timestamp() if now is None else now
    hint = _retry_after(headers, now)
    if hint is None:
        hint = _reset_hint(headers, now)
    if hint is None:
        relayed = {
            name.lower().removeprefix(RELAYED_PREFIX): value
            for name, value in headers.items()
            if name.lower().startswith(RELAYED_PREFIX)
        }
        if relayed:
            hint = _retry_after(relayed, now)
            hint = hint if hint is not None else _reset_hint(relayed, now)
    return hint


def backoff_delay(
    attempt: int, policy: RetryPolicy, hint: float | None, rng: random.Random
) -> float:
    """Seconds to wait after failed attempt number `attempt` (1-based).

    Without a hint: exponential backoff with "equal jitter" (half fixed, half random), so that
    retries never bunch up and never come back instantly. With a hint: the hint, plus up to
    10 % (at most 1 s) so that the hundreds of calls told the same Retry-After do not all
    return in the same millisecond; never sooner than the server asked.
    """
    if hint is not None:
        return hint + rng.uniform(0.0, min(1.0, 0.1 * hint))
    ceiling = min(policy.backoff_max_s, policy.backoff_base_s * 2 ** (attempt - 1))
    return ceiling / 2 + rng.uniform(0.0, ceiling / 2)
