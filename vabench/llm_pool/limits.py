"""Per-endpoint limits: requests in flight, requests per period, tokens per period.

A `RateBudget` enforces one rate limit two ways at once:

- a sliding window: the amounts admitted in any window of one period never add up to more
  than the limit (a provider's "per minute" taken literally, whatever minute you pick). The
  window is 1 % longer than the period, and at least `MIN_SLACK_S` longer, so that the jitter
  between our admission and the provider's arrival clock does not look like an excess on its
  side (that jitter is absolute: a busy host's processes, a limit board's round trip).
- a token bucket (refill limit/period per second, capacity `burst_s` seconds of that), which
  spreads admissions out: providers enforce per-minute limits on shorter slices (OpenAI:
  "60,000 RPM may be enforced as 1,000 requests per second"), so a whole minute's budget in
  one burst would be refused even though the minute total is fine. An amount larger than the
  bucket (one big request under a small TPM) waits for a full bucket and leaves it in debt.

Tokens are estimated at admission and `settle`d to the reported usage after the call: a
refund frees window and bucket at once, an underestimate is charged when it becomes known.

`RateLimiter` pairs a request budget with a token budget behind one FIFO lock, so waiting
calls are admitted in arrival order (a large call is not starved by a stream of small ones).
`ConcurrencyLimiter` bounds requests in flight, optionally adapting the bound (AIMD: halve on
429/529, at most once per cooldown; grow by one per limit's worth of successes).

Limits kept for several processes at once: `vabench.llm_pool.shared_limits`.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass

WINDOW_MARGIN = 0.01
MIN_SLACK_S = 0.25
"""The least a client's window exceeds the period by (short periods: tests, benchmarks)."""


class _Entry:
    __slots__ = ("amount", "at", "live")

    def __init__(self, at: float, amount: float):
        self.at = at
        self.amount = amount
        self.live = True  # still counted in the window sum


class RateBudget:
    """One limit: at most `limit` units per `period_s`, smoothed over `burst_s`. `margin`
    lengthens the window (clients keep the default; an enforcing server uses 0)."""

    def __init__(
        self, limit: float, period_s: float, burst_s: float = 1.0, margin: float = WINDOW_MARGIN
    ):
        if limit <= 0 or period_s <= 0 or burst_s <= 0 or margin < 0:
            raise ValueError("limit, period_s and burst_s must be positive, margin not negative")
        self.limit = float(limit)
        self.period_s = float(period_s)
        self.window_s = self.period_s * (1 + margin)
        if margin > 0:
            self.window_s = max(self.window_s, self.period_s + MIN_SLACK_S)
        self.rate = self.limit / self.period_s
        self.capacity = min(self.limit, max(1.0, self.rate * burst_s))
        self._level = self.capacity
        self._updated: float | None = None
        self._log: deque[_Entry] = deque()
        self._in_window = 0.0

    def _expire(self, now: float) -> None:
        while self._log and self._log[0].at <= now - self.window_s:
            entry = self._log.popleft()
            entry.live = False
            self._in_window -= entry.amount

    def _refill(self, now: float) -> None:
        if self._updated is not None:
            self._level = min(self.capacity, self._level + (now - self._updated) * self.rate)
        self._updated = now

    def wait_time(self, amount: float, now: float) -> float:
        """Seconds until `amount` could be admitted (0 if now). `amount` must not exceed the
        limit (`RateLimiter.acquire` checks)."""
        self._expire(now)
        self._refill(now)
        bucket_wait = max(0.0, (min(amount, self.capacity) - self._level) / self.rate)
        excess = self._in_window + amount - self.limit
        window_wait = 0.0
        if excess > 1e-9:
            for entry in self._log:
                excess -= entry.amount
                if excess <= 1e-9:
                    window_wait = entry.at + self.window_s - now
                    break
        return max(bucket_wait, window_wait)

    def take(self, amount: float, now: float) -> _Entry:
        entry = _Entry(now, amount)
        self._log.append(entry)
        self._in_window += amount
        self._level -= amount
        return entry

    def settle(self, entry: _Entry, actual: float) -> None:
        """Replace an admitted estimate by the actual amount."""
        delta = actual - entry.amount
        entry.amount = actual
        if entry.live:
            self._in_window += delta
        self._level = min(self.capacity, self._level - delta)

    def remaining(self, now: float) -> tuple[float, float]:
        """(units left in the current window, seconds until the oldest admission expires)."""
        self._expire(now)
        reset = self._log[0].at + self.window_s - now if self._log else 0.0
        return self.limit - self._in_window, reset


@dataclass
class Admission:
    """A granted call: when, and the token entry to settle after the call."""

    at: float
    tokens: float
    _token_entry: _Entry | None
    lease: int | None = None
    """The board's admission this call came with (`SharedLimits`); None for a local one."""


class RateLimiter:
    """Requests and tokens per period for one endpoint; either limit may be absent."""

    def __init__(
        self,
        rpm: float | None,
        tpm: float | None,
        *,
        period_s: float = 60.0,
        burst_s: float = 1.0,
    ):
        self.requests = RateBudget(rpm, period_s, burst_s) if rpm else None
        self.tokens = RateBudget(tpm, period_s, burst_s) if tpm else None
        self._lock = asyncio.Lock()

    @property
    def active(self) -> bool:
        return self.requests is not None or self.tokens is not None

    def check_fits(self, tokens: float) -> None:
        """Raise ValueError if one call alone exceeds the token limit: it could never run."""
        if self.tokens is not None:
            check_fits(tokens, self.tokens.limit, self.tokens.period_s)

    async def acquire(self, tokens: float) -> Admission:
        """Wait until one request of `tokens` estimated tokens fits both limits, then admit it.
        Cancellation while waiting admits nothing."""
        self.check_fits(tokens)
        loop = asyncio.get_running_loop()
        async with self._lock:
            while True:
                now = loop.time()
                wait = 0.0
                if self.requests is not None:
                    wait = self.requests.wait_time(1.0, now)
                if self.tokens is not None:
                    wait = max(wait, self.tokens.wait_time(tokens, now))
                if wait <= 0.0:
                    break
                await asyncio.sleep(wait)
            if self.requests is not None:
                self.requests.take(1.0, now)
            entry = self.tokens.take(tokens, now) if self.tokens is not None else None
            return Admission(now, tokens, entry)

    def settle(self, admission: Admission, actual_tokens: float) -> None:
        if self.tokens is not None and admission._token_entry is not None:
            self.tokens.settle(admission._token_entry, actual_tokens)
            admission.tokens = actual_tokens


def check_fits(tokens: float, tpm: float | None, period_s: float) -> None:
    """Raise ValueError if one call of `tokens` exceeds a token limit of `tpm` per period."""
    if tpm is not None and tokens > tpm:
        raise ValueError(
            f"one call is estimated at {tokens:.0f} tokens, above the endpoint's limit of "
            f"{tpm:.0f} per {period_s:g} s (limits.tpm); raise the limit or lower "
            "max_output_tokens"
        )


class Slots:
    """What the pool holds a call's concurrency slot through: `acquire`, `release` and the
    `slot` context around them (this process's `ConcurrencyLimiter`, or the slots several
    processes lease from one board, `shared_limits.LeasedSlots`)."""

    async def acquire(self, *, priority: bool = False) -> None:
        raise NotImplementedError

    def release(self) -> None:
        raise NotImplementedError

    @asynccontextmanager
    async def slot(self, *, priority: bool = False) -> AsyncIterator[None]:
        await self.acquire(priority=priority)
        try:
            yield
        finally:
            self.release()


class ConcurrencyLimiter(Slots):
    """A semaphore whose bound can move (adaptive concurrency) and that lets retries jump the
    queue (a call that already waited once should not queue behind thousands of new ones)."""

    DECREASE = 0.5
    COOLDOWN_S = 2.0  # one overload episode shrinks the bound once, not once per 429 in it

    def __init__(self, limit: int, *, adaptive: bool = False, floor: int = 1):
        self.ceiling = limit
        self.floor = min(floor, limit)
        self.adaptive = adaptive
        self.limit = float(limit)
        self.in_flight = 0
        self._waiters: deque[asyncio.Future[None]] = deque()
        self._last_decrease = float("-inf")

    @property
    def queued(self) -> int:
        return len(self._waiters)

    @property
    def bound(self) -> int:
        """Slots currently allowed (the adaptive limit, rounded down, at least the floor)."""
        return max(self.floor, int(self.limit))

    async def acquire(self, *, priority: bool = False) -> None:
        if not self._waiters and self.in_flight < self.bound:
            self.in_flight += 1
            return
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        if priority:
            self._waiters.appendleft(waiter)
        else:
            self._waiters.append(waiter)
        try:
            await waiter
        except asyncio.CancelledError:
            if waiter.done() and not waiter.cancelled():
                self.release()  # the slot was handed over just as we were cancelled
            elif waiter in self._waiters:  # (_wake may already have dropped it)
                self._waiters.remove(waiter)
            raise

    def try_acquire(self) -> bool:
        """Take a slot if one is free and nobody waits for it; never waits."""
        if self._waiters or self.in_flight >= self.bound:
            return False
        self.in_flight += 1
        return True

    def release(self) -> None:
        self.in_flight -= 1
        self._wake()

    def _wake(self) -> None:
        while self._waiters and self.in_flight < self.bound:
            waiter = self._waiters.popleft()
            if not waiter.done():
                self.in_flight += 1
                waiter.set_result(None)

    def on_overload(self, now: float) -> None:
        """The endpoint said 429/529: multiplicative decrease, once per cooldown."""
        if not self.adaptive or now - self._last_decrease < self.COOLDOWN_S:
            return
        self._last_decrease = now
        self.limit = max(float(self.floor), self.limit * self.DECREASE)

    def on_success(self) -> None:
        """Additive increase: about one more slot per `limit` successful calls."""
        if self.adaptive and self.limit < self.ceiling:
            self.limit = min(float(self.ceiling), self.limit + 1.0 / self.limit)
            self._wake()
