"""The client pool: `await pool.complete(endpoint_name, request)` from any number of episodes.

Each endpoint has one aiohttp session (its own connection pool, sized to its concurrency,
in `transport.Transport`), one `ConcurrencyLimiter` and one `RateLimiter`, shared by every
episode that calls it. One call goes through these steps, each attempt holding one
concurrency slot:

    estimate tokens -> slot -> wait out any server-requested pause -> rate admission
    -> POST -> parse -> settle tokens to the reported usage -> CompletionResult

and on a retryable failure releases the slot, backs off (the server's hint, else exponential
with jitter) and queues again ahead of new calls. The total deadline runs from the call's
first admission (time spent queueing behind other calls of a saturated endpoint is not the
endpoint's fault); the attempt ceiling counts HTTP attempts.

Every call ends exactly once: a `CompletionResult`, an `InfrastructureError` (retries ran
out), a `RequestRejected` (a non-retryable 4xx, or `EndpointUnreachable`: no connection could
be made before the endpoint ever answered), or the caller's cancellation. Usage and cost
are counted once, from the successful attempt.
"""

from __future__ import annotations

import asyncio
import logging
import os
import random
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

from pydantic import SecretStr

from vabench.llm_pool.apis import get_adapter
from vabench.llm_pool.apis.base import encode_body
from vabench.llm_pool.config import (
    ConfigError,
    GenerationOptions,
    ModelEndpoint,
    load_endpoints,
)
from vabench.llm_pool.errors import (
    EndpointUnreachable,
    InfrastructureError,
    RequestRejected,
    SpendCapReached,
    context_exceeded,
)
from vabench.llm_pool.heap import keep_trimmed
from vabench.llm_pool.limits import ConcurrencyLimiter, RateLimiter
from vabench.llm_pool.messages import ChatRequest, CompletionResult, ParsedResponse, Usage
from vabench.llm_pool.retry import RetryDecision, backoff_delay
from vabench.llm_pool.shared_limits import SharedLimits
from vabench.llm_pool.spend import CapReached, Caps, LocalCaps, Reservation, SpendCaps
from vabench.llm_pool.tokens import estimate_input_tokens
from vabench.llm_pool.transport import Failure, Transport

# asyncio.timeout tells our own deadline from a caller's cancellation; wait_for (3.11 and
# before) can swallow a cancellation that races with its timeout, leaving a task that ignores
# cancel(). Python 3.10 gets the same context manager from aiohttp's own dependency.
if sys.version_info >= (3, 11):
    from asyncio import timeout
else:
    from async_timeout import timeout

log = logging.getLogger("vabench.llm_pool")

TIMEOUTS_TO_STOP = 2
"""Attempts timed out, with nothing ever answered, after which the endpoint counts as
unreachable (one slow first answer is retried once)."""


@dataclass
class CallCounts:
    """What one endpoint's calls have come to (`EndpointStats` adds its live state)."""

    started: int = 0
    """Calls admitted past the endpoint's limits."""
    succeeded: int = 0
    failed: int = 0
    """Calls that ended in an infrastructure error once their retries were spent."""
    rejected: int = 0
    """Calls the provider refused (a non-retryable 4xx), or that could never be sent."""
    cancelled: int = 0
    attempts: int = 0
    """HTTP attempts of every call, retries included."""
    rate_limited: int = 0
    """Attempts the provider turned away with a rate limit (retried after its wait)."""
    usage: Usage = field(default_factory=Usage)
    cost_usd: float = 0.0


@dataclass
class EndpointStats(CallCounts):
    """A snapshot of one endpoint's counters and state (for progress displays and reports)."""

    name: str = ""
    in_flight: int = 0
    queued: int = 0
    concurrency_limit: int = 0


@dataclass
class _Call:
    """The state of one call across its attempts."""

    request: ChatRequest
    options: GenerationOptions
    estimate: int
    started: float
    deadline: float | None = None
    attempt: int = 0
    failures: list[str] = field(default_factory=list)
    body: bytes | None = None
    rate_waits: int = 0
    """Attempts answered 429/529: waits, not failures (`max_attempts` counts the others)."""


class EndpointClient:
    """Calls to one endpoint; created by `LLMPool`, shared by every episode using it."""

    def __init__(
        self,
        config: ModelEndpoint,
        api_key: SecretStr | None,
        rng: random.Random,
        shared: SharedLimits | None = None,
    ):
        self.config = config
        self.adapter = get_adapter(config.api)
        self._transport = Transport(config, self.adapter, api_key)
        self.url = self._transport.url
        self._rng = rng
        limits = config.limits
        self._shared = shared
        if shared is not None:  # one set of limits for several processes (limits.py)
            self.concurrency: ConcurrencyLimiter | Any = shared.concurrency
            self.rate: RateLimiter | Any = shared.rate
        else:
            self.concurrency = ConcurrencyLimiter(
                limits.max_concurrency, adaptive=limits.adaptive, floor=limits.min_concurrency
            )
            self.rate = RateLimiter(
                limits.rpm, limits.tpm, period_s=limits.period_s, burst_s=limits.burst_s
            )
        self._counters = CallCounts()
        self.spend_caps: Caps | None = None
        """`limits.max_cost_usd` kept by the sweep (`LLMPool.set_spend_caps`, or the limit
        board's, `LLMPool(spend_caps=...)`); None: no cap."""
        self._paused_until = 0.0
        self._closed = False
        self._warned_no_usage = False
        self._answered = False
        """Whether any reply (any status) came back: connection failures are then transient."""
        self._unanswered_timeouts = 0
        """Attempts that timed out while the endpoint had never answered (`TIMEOUTS_TO_STOP`)."""
        self._rate_waits = 0
        """429s without a hint in a row: each pauses the endpoint twice as long (`_rate_wait`)."""

    @property
    def name(self) -> str:
        return self.config.name

    def __repr__(self) -> str:
        return f"EndpointClient({self.name!r}, {self.config.api}, {self.url})"

    def stats(self) -> EndpointStats:
        c = self._counters
        return EndpointStats(
            **{f.name: getattr(c, f.name) for f in fields(c)},
            name=self.name,
            in_flight=self.concurrency.in_flight,
            queued=self.concurrency.queued,
            concurrency_limit=self.concurrency.bound,
        )

    async def complete(self, request: ChatRequest) -> CompletionResult:
        """One call with retries; see the module docstring for the outcomes."""
        if self._closed:
            raise RuntimeError(f"{self.name}: the pool is closed")
        options = self.config.generation.merge(request.options)
        self.adapter.check_options(options)
        estimate = estimate_input_tokens(request, self.adapter.image_tokens)
        estimate += options.resolved_max_output_tokens
        try:
            self.rate.check_fits(estimate)
        except ValueError as err:
            self._counters.rejected += 1
            raise RequestRejected(
                self.name, str(err), status=413, attempts=0, elapsed_s=0.0
            ) from None
        bound = self._upper_bound_usd(estimate, options.resolved_max_output_tokens)
        held: Reservation | None = None
        if self.spend_caps is not None:
            reserved = await self.spend_caps.reserve(self.name, bound)
            if isinstance(reserved, CapReached):
                self._counters.rejected += 1
                raise SpendCapReached(self.name, reserved)
            held = reserved
        self._counters.started += 1
        call = _Call(request, options, estimate, asyncio.get_running_loop().time())
        cost = 0.0
        try:
            result = await self._call(call)
            cost = result.cost_usd
        except InfrastructureError:
            self._counters.failed += 1
            raise
        except RequestRejected:
            self._counters.rejected += 1
            raise
        except asyncio.CancelledError:
            self._counters.cancelled += 1
            raise
        finally:
            if held is not None:
                held.settle(cost)
        self._counters.succeeded += 1
        return result

    def _upper_bound_usd(self, estimate: int, max_output: int) -> float:
        """The most a call of `estimate` tokens (input estimate + output limit) may cost: its
        input at the dearest input price, its whole output limit at the output price."""
        p = self.config.prices
        if p is None:
            return 0.0
        dearest_input = max(p.input, p.cache_write or 0.0, p.cached_input or 0.0)
        return ((estimate - max_output) * dearest_input + max_output * p.output) / 1e6

    async def _call(self, call: _Call) -> CompletionResult:
        while True:
            call.attempt += 1
            async with self.concurrency.slot(priority=call.attempt > 1):
                outcome = await self._attempt_in_slot(call)
                if isinstance(outcome, CompletionResult):
                    return outcome
                decision = self._note_failure(call, outcome)
            await self._back_off(call, decision)  # outside the slot: others may use it

    async def _attempt_in_slot(self, call: _Call) -> CompletionResult | Failure:
        """Admission, then one HTTP attempt, while holding a concurrency slot."""
        loop = asyncio.get_running_loop()
        retry = self.config.retry
        if call.deadline is None:  # the total deadline runs from the first admission
            call.deadline = loop.time() + retry.total_timeout_s
        if self._closed:
            raise self._infra(call, "the pool was closed", attempts=call.attempt - 1)
        try:
            async with timeout(max(0.0, call.deadline - loop.time())):
                admission = await self._admit(call.estimate)
        except asyncio.TimeoutError:
            raise self._infra(
                call,
                f"total deadline of {retry.total_timeout_s:g} s passed while waiting for the "
                "endpoint's rate limits",
                attempts=call.attempt - 1,
            ) from None
        if call.body is None:  # built once admitted: queued calls hold no encoded bodies
            call.body = encode_body(
                self.adapter.build_body(self.config, call.request, call.options)
            )
        attempt_timeout = min(retry.request_timeout_s, max(0.001, call.deadline - loop.time()))
        self._counters.attempts += 1
        sent = loop.time()
        outcome = await self._transport.post(call.body, attempt_timeout)
        if not (isinstance(outcome, Failure) and (outcome.unreachable or outcome.timed_out)):
            self._answered = True
        if isinstance(outcome, Failure):
            # No usage came back; the provider may have counted the estimate: keep it.
            return outcome
        if outcome.usage_reported:
            self.rate.settle(admission, outcome.usage.total_tokens)
        elif not self._warned_no_usage:  # the estimate stays on the TPM books
            self._warned_no_usage = True
            log.warning(
                "%s: a reply without usage: its tokens count as 0 (cost and token totals of "
                "this endpoint understate; some local servers omit usage). Said once.",
                self.name,
            )
        self.concurrency.on_success()
        self._rate_waits = 0
        return self._result(call, outcome, loop.time() - sent)

    def _note_failure(self, call: _Call, failure: Failure) -> RetryDecision:
        """Record a failed attempt; raise at once if it must not be retried."""
        loop = asyncio.get_running_loop()
        call.failures.append(failure.line)
        decision = failure.decision
        where = self.config.base_url or self.url
        if failure.unreachable and not self._answered:
            hint = (
                f"the endpoint at {where} (base_url of model {self.name!r}) answered that it "
                "cannot reach the server behind it: check the gateway's upstream"
                if failure.status is not None
                else f"check that a server is running at {where} (base_url of model "
                f"{self.name!r}) and that this machine can reach it"
            )
            raise EndpointUnreachable(
                self.name,
                failure.line,
                attempts=call.attempt,
                elapsed_s=loop.time() - call.started,
                hint=hint,
            )
        if failure.timed_out and not self._answered:
            self._unanswered_timeouts += 1
            if self._unanswered_timeouts >= TIMEOUTS_TO_STOP:
                timeout_s = self.config.retry.request_timeout_s
                raise EndpointUnreachable(
                    self.name,
                    f"every call of model {self.name!r} timed out after {timeout_s:g} s "
                    f"({self._unanswered_timeouts} attempts, none answered)",
                    attempts=call.attempt,
                    elapsed_s=loop.time() - call.started,
                    hint=f"check that the server at {where} serves model "
                    f"{self.config.provider_model!r}, or raise retry.request_timeout_s of "
                    f"model {self.name!r}",
                )
        fatal_meaning = failure.meaning in ("key", "model") and (
            (failure.status or 0) < 500 or self._counters.succeeded == 0
        )
        if not decision.retry or fatal_meaning:
            status = failure.status or 0
            fatal, hint = self._refusal(status, failure.meaning)
            if context_exceeded(status, failure.line):  # the episode's failure, not the sweep's
                fatal, hint = False, ""
            raise RequestRejected(
                self.name,
                call.failures[-1],
                status=status,
                attempts=call.attempt,
                elapsed_s=loop.time() - call.started,
                fatal=fatal,
                hint=hint,
                meaning=failure.meaning,
            )
        if decision.kind == "rate_limit":
            self._counters.rate_limited += 1
            self.concurrency.on_overload(loop.time())
            call.rate_waits += 1  # a wait, not a failure: the deadline bounds them
            if decision.retry_after is None:  # a gateway's 429 without a hint: wait longer each
                decision = replace(decision, retry_after=self._rate_wait())
            if decision.retry_after is not None:  # the endpoint, not just this call, waits
                self._paused_until = max(self._paused_until, loop.time() + decision.retry_after)
                if self._shared is not None:  # and so does every process sharing its limits
                    self._shared.pause(decision.retry_after)
        return decision

    def _rate_wait(self) -> float:
        """The pause after a 429 that named no wait: the backoff base, doubled for each such
        429 in a row (back to the base after a success), at most the backoff ceiling."""
        retry = self.config.retry
        self._rate_waits += 1
        return min(retry.backoff_max_s, retry.backoff_base_s * 2 ** (self._rate_waits - 1))

    def _refusal(self, status: int, meaning: str | None = None) -> tuple[bool, str]:
        """Whether a refusal (a non-retryable status, or a body naming the key or the model)
        means the endpoint cannot serve the sweep at all (see `errors.RequestRejected`), and
        what to check: only settings of the model's API."""
        c = self.config
        if meaning == "model":
            return True, (
                f"the endpoint does not know the model {c.provider_model!r}: check `model` "
                f"(default: the name) of model {c.name!r} against the endpoint's list"
            )
        if status in (401, 403) or meaning == "key":
            if c.api_key_env:
                where = (
                    f"the key in the environment variable {c.api_key_env} (api_key_env of "
                    f"model {c.name!r})"
                )
            else:
                where = f"model {c.name!r} has no api_key_env: the endpoint wants a key"
                if status >= 500:  # read from a bare 500 to a keyless call (`Transport`)
                    where += " (if it needs none, the server's log says what failed)"
            return True, f"check {where}"
        if status == 404:
            return True, f"check the model id {c.provider_model!r} and the URL {self.url}"
        if status == 400 and self._counters.succeeded == 0:
            fields = "generation options"
            if self.adapter.output_field_choice:
                fields += " and max_tokens_field"
            return True, (
                f"the endpoint has not accepted one request of model {c.name!r}: check its "
                f"{fields} against what the endpoint takes"
            )
        return False, ""

    async def _back_off(self, call: _Call, decision: RetryDecision) -> None:
        """Wait before the next attempt, or raise if the attempts or the time are spent."""
        retry = self.config.retry
        if call.attempt - call.rate_waits >= retry.max_attempts:
            raise self._infra(
                call, f"gave up after {call.attempt} attempts; last: {call.failures[-1]}"
            )
        delay = backoff_delay(call.attempt, retry, decision.retry_after, self._rng)
        assert call.deadline is not None
        if asyncio.get_running_loop().time() + delay > call.deadline:
            raise self._infra(
                call,
                f"a {delay:.1f} s backoff would pass the total deadline of "
                f"{retry.total_timeout_s:g} s; last: {call.failures[-1]}",
            )
        log.info(
            "%s: attempt %d failed (%s); retrying in %.2f s",
            self.name,
            call.attempt,
            call.failures[-1],
            delay,
        )
        await asyncio.sleep(delay)

    async def _admit(self, estimate: int):
        loop = asyncio.get_running_loop()
        while (pause := self._paused_until - loop.time()) > 0:
            await asyncio.sleep(pause)
        return await self.rate.acquire(estimate)

    def _result(self, call: _Call, parsed: ParsedResponse, latency: float) -> CompletionResult:
        prices = self.config.prices
        cost = parsed.usage.cost(prices) if prices is not None else 0.0
        self._counters.usage += parsed.usage
        self._counters.cost_usd += cost
        return CompletionResult(
            endpoint=self.name,
            text=parsed.text,
            finish_reason=parsed.finish_reason,
            raw_finish_reason=parsed.raw_finish_reason,
            usage=parsed.usage,
            cost_usd=cost,
            latency_s=latency,
            elapsed_s=asyncio.get_running_loop().time() - call.started,
            attempts=call.attempt,
            model=parsed.model,
            response_id=parsed.response_id,
            reasoning=parsed.reasoning,
            function_calls=parsed.function_calls,
            failures=tuple(call.failures),
        )

    def _infra(self, call: _Call, message: str, attempts: int | None = None) -> InfrastructureError:
        return InfrastructureError(
            self.name,
            message,
            attempts=call.attempt if attempts is None else attempts,
            elapsed_s=asyncio.get_running_loop().time() - call.started,
            failures=tuple(call.failures),
        )

    async def close(self) -> None:
        self._closed = True
        await self._transport.close()


class LLMPool:
    """All endpoints of a sweep. Create it inside the event loop that will use it (or use
    `async with LLMPool(...) as pool`), call `complete` from any number of tasks, `close` at
    the end. Keys are read from the environment once, here, so that a missing key stops a
    sweep before its first episode."""

    def __init__(
        self,
        endpoints: Iterable[ModelEndpoint | Mapping[str, Any]],
        *,
        environ: Mapping[str, str] | None = None,
        seed: int | None = None,
        shared_limits: Callable[[ModelEndpoint], SharedLimits | None] | None = None,
        spend_caps: Caps | None = None,
    ):
        """`shared_limits(endpoint)`: the limits an endpoint shares with other processes, or
        None for its own (the default for every endpoint). `spend_caps`: the spend caps kept
        for several processes (the limit board's); `set_spend_caps` then changes nothing."""
        environ = os.environ if environ is None else environ
        keep_trimmed()  # else a long run's read buffers hold heap pages (heap.py)
        rng = random.Random(seed)
        self._clients: dict[str, EndpointClient] = {}
        for i, ep in enumerate(load_endpoints(endpoints)):
            key = None
            if ep.api_key_env is not None:
                value = environ.get(ep.api_key_env)
                if not value:
                    raise ConfigError(
                        f"models[{i}].api_key_env",
                        f"environment variable {ep.api_key_env} is not set (endpoint {ep.name!r})",
                    )
                key = SecretStr(value)
            shared = shared_limits(ep) if shared_limits is not None else None
            self._clients[ep.name] = EndpointClient(ep, key, random.Random(rng.random()), shared)
        self.shared_spend = spend_caps is not None
        """Whether the spend caps are kept for several processes (`spend_caps`)."""
        for client in self._clients.values():
            client.spend_caps = spend_caps

    def set_spend_caps(self, caps: SpendCaps | None) -> None:
        """Keep `caps` (`limits.max_cost_usd`) in this process before every call of every
        endpoint from now on; None lifts them. A pool whose caps are shared keeps those."""
        if self.shared_spend:
            return
        kept = LocalCaps(caps) if caps is not None else None
        for client in self._clients.values():
            client.spend_caps = kept

    @property
    def names(self) -> list[str]:
        return list(self._clients)

    def endpoint(self, name: str) -> EndpointClient:
        try:
            return self._clients[name]
        except KeyError:
            raise KeyError(f"unknown endpoint {name!r}; configured: {self.names}") from None

    async def complete(self, endpoint: str, request: ChatRequest) -> CompletionResult:
        """Send `request` to the named endpoint; see `EndpointClient.complete`."""
        return await self.endpoint(endpoint).complete(request)

    def stats(self) -> dict[str, EndpointStats]:
        return {name: client.stats() for name, client in self._clients.items()}

    async def close(self) -> None:
        """Close every connection. Calls still running fail as infrastructure errors; cancel
        or finish them first."""
        await asyncio.gather(*(c.close() for c in self._clients.values()))

    async def __aenter__(self) -> LLMPool:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
