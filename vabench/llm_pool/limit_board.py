"""One place for each endpoint's limits across a sweep's processes: the limit board.

Every worker process (`vabench.sweep.process_executor`) and engine actor of a Ray sweep
(`vabench.sweep.ray_engine`) has its own LLM pool; without this, N of them would each keep an
endpoint's RPM, TPM and concurrency, and send N times what the provider allows. The
`LimitBoard` holds, per endpoint of the sweep that is not served by the embedded server (each
process runs its own embedded server, whose limits are its own):

- the endpoint's `ConcurrencyLimiter` (adaptive when the config says so, moved by the
  overloads and successes every actor reports), with the slots each actor holds;
- its RPM and TPM windows (`RateBudget`, exactly as a single pool keeps them; the tokens of an
  admission settled to the reported usage);
- a pause: a Retry-After seen by any actor holds every actor's next admission;

and, for the whole sweep, its spend caps (`llm_pool.spend.SpendCaps`): every call's upper bound
is reserved on the board before it is sent (`BoardSpend`), so the caps hold exactly however many
processes spend.

The pools reach the board through `llm_pool.shared_limits.SharedLimits` (the client side, which
batches the waiting calls of one process into one request); `LimiterActor` is the board as a
Ray actor (one per sweep, on the driver's node, owned by the driver and gone with it), and
`RayChannel` the client's way to it; worker processes reach the board in their parent through a
local socket (`board_socket`). `forget(holder)` frees what a dead process held (its slots; its
spend reservations are counted as spent, as the provider may have billed them): the driver
calls it when an actor dies, the socket when a worker's connection closes.

Admissions are taken when the board grants them and the request leaves the actor a moment
later (a round trip, milliseconds); the windows are the pool's own, 1 % longer than the
provider's period (`limits.WINDOW_MARGIN`), which covers that delay.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
from collections.abc import AsyncIterator, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from vabench.llm_pool.config import Limits, ModelEndpoint
from vabench.llm_pool.limits import ConcurrencyLimiter, RateBudget
from vabench.llm_pool.shared_limits import LimitChannel, SharedLimits
from vabench.llm_pool.spend import CapReached, Reservation, SpendCaps


class _Endpoint:
    """The board's state for one endpoint."""

    def __init__(self, limits: Limits):
        self.limits = limits
        self.concurrency = ConcurrencyLimiter(
            limits.max_concurrency, adaptive=limits.adaptive, floor=limits.min_concurrency
        )
        period, burst = limits.period_s, limits.burst_s
        self.requests = RateBudget(limits.rpm, period, burst) if limits.rpm else None
        self.tokens = RateBudget(limits.tpm, period, burst) if limits.tpm else None
        self.lock = asyncio.Lock()  # admissions in arrival order, as `RateLimiter`'s
        self.paused_until = 0.0
        self.held: collections.Counter[str] = collections.Counter()
        self.leases: dict[int, Any] = {}  # lease -> its token entry
        self.lease_times: collections.deque[tuple[float, int]] = collections.deque()
        self.admitted = 0
        self.granted = 0

    def fits(self, requests: int, tokens: float, now: float) -> bool:
        """Whether `requests` more requests of `tokens` tokens in all fit now, within the
        window and the burst (an amount above the burst is admitted only alone)."""
        for budget, amount in ((self.requests, requests), (self.tokens, tokens)):
            if budget is None:
                continue
            if budget.wait_time(amount, now) > 0:
                return False
            if requests > 1 and amount > budget.capacity:
                return False
        return True

    def wait_time(self, tokens: float, now: float) -> float:
        wait = 0.0
        if self.requests is not None:
            wait = self.requests.wait_time(1.0, now)
        if self.tokens is not None:
            wait = max(wait, self.tokens.wait_time(tokens, now))
        return wait

    def forget_old_leases(self, now: float) -> None:
        """Settlements come within a call's lifetime; a lease older than two windows will get
        none (its call failed and kept its estimate, as a single pool does)."""
        horizon = 2 * self.limits.period_s * 1.1 + 600.0
        while self.lease_times and self.lease_times[0][0] < now - horizon:
            self.leases.pop(self.lease_times.popleft()[1], None)


class LimitBoard:
    """The limits of the endpoints `limits` (name -> `Limits`) for every process of a sweep
    (see the module docstring). Runs in one asyncio loop; every method is called there."""

    def __init__(
        self, limits: Mapping[str, Limits | Mapping[str, Any]], spend: SpendCaps | None = None
    ):
        self._endpoints = {
            name: _Endpoint(v if isinstance(v, Limits) else Limits.model_validate(v))
            for name, v in limits.items()
        }
        self.spend = spend
        self._reserved: dict[tuple[str, int], tuple[str, float]] = {}
        """(holder, its reservation's number) -> (model, upper bound) of the calls in flight."""
        self._forgotten: set[str] = set()
        self._next_lease = 0

    def _endpoint(self, name: str) -> _Endpoint:
        try:
            return self._endpoints[name]
        except KeyError:
            raise KeyError(f"the limit board has no endpoint {name!r}") from None

    async def slots(self, endpoint: str, holder: str, want: int, priority: bool) -> tuple[int, int]:
        """Wait for one concurrency slot of `endpoint`, then take up to `want` in all while
        more are free and nobody waits; returns (slots granted, the endpoint's bound). 0 slots
        for a forgotten holder."""
        ep = self._endpoint(endpoint)
        bound = ep.concurrency.bound
        if holder in self._forgotten:
            return 0, bound
        await ep.concurrency.acquire(priority=priority)
        granted = 1
        while granted < want and ep.concurrency.try_acquire():
            granted += 1
        if holder in self._forgotten:  # it died while it waited
            for _ in range(granted):
                ep.concurrency.release()
            return 0, ep.concurrency.bound
        ep.held[holder] += granted
        ep.granted += granted
        return granted, ep.concurrency.bound

    async def admit(self, endpoint: str, holder: str, estimates: list[float]) -> tuple[int, int]:
        """Wait out the endpoint's pause, then until the first of `estimates` (the estimated
        tokens of the calls waiting, in order) fits the rate windows; admit it and as many of
        the next ones as fit now. Returns (calls admitted, the lease their tokens are settled
        against); (0, -1) for a forgotten holder."""
        ep = self._endpoint(endpoint)
        loop = asyncio.get_running_loop()
        async with ep.lock:
            while True:
                if holder in self._forgotten:
                    return 0, -1
                now = loop.time()
                wait = max(ep.paused_until - now, ep.wait_time(estimates[0], now))
                if wait <= 0:
                    break
                await asyncio.sleep(wait)
            n, tokens = 1, estimates[0]
            while n < len(estimates) and ep.fits(n + 1, tokens + estimates[n], now):
                tokens += estimates[n]
                n += 1
            if ep.requests is not None:
                ep.requests.take(float(n), now)
            self._next_lease += 1
            if ep.tokens is not None:
                ep.leases[self._next_lease] = ep.tokens.take(tokens, now)
                ep.lease_times.append((now, self._next_lease))
                ep.forget_old_leases(now)
            ep.admitted += n
            return n, self._next_lease

    def report(
        self,
        endpoint: str,
        holder: str,
        returned: int,
        successes: int,
        overloads: int,
        settles: list[tuple[int, float]],
    ) -> None:
        """Slots a holder gave back, calls that succeeded, overloads (429/529) it saw, and
        token settlements (lease, reported usage minus estimate)."""
        ep = self._endpoint(endpoint)
        back = min(returned, ep.held[holder])
        ep.held[holder] -= back
        for _ in range(back):
            ep.concurrency.release()
        for _ in range(successes):
            ep.concurrency.on_success()
        if overloads:
            ep.concurrency.on_overload(asyncio.get_running_loop().time())
        for lease, delta in settles:
            entry = ep.leases.get(lease)
            if entry is not None and ep.tokens is not None:
                ep.tokens.settle(entry, entry.amount + delta)

    def pause(self, endpoint: str, seconds: float) -> None:
        """The endpoint asked one holder for `seconds` of quiet: every admission waits."""
        ep = self._endpoint(endpoint)
        ep.paused_until = max(ep.paused_until, asyncio.get_running_loop().time() + seconds)

    def hold(self, holder: str, number: int, model: str, upper_bound: float) -> CapReached | None:
        """Reserve the `upper_bound` of a call of `model` (`holder`'s reservation `number`);
        the cap it would cross, or None when reserved. Runs at once, in the order sent."""
        if holder in self._forgotten:
            raise RuntimeError(f"the board no longer serves {holder}")
        if self.spend is None:
            return None
        reached = self.spend.hold(model, upper_bound)
        if reached is None:
            self._reserved[(holder, number)] = (model, upper_bound)
        return reached

    def settle_spend(self, holder: str, number: int, cost: float) -> None:
        """`holder`'s reservation `number` ended, costing `cost` (an unknown one: refused, or
        already counted when its holder was forgotten)."""
        held = self._reserved.pop((holder, number), None)
        if held is not None and self.spend is not None:
            self.spend.settle(held[0], held[1], cost)

    def forget(self, holder: str) -> None:
        """`holder` is gone: free its slots, count its reservations as spent, and never grant
        it anything again."""
        self._forgotten.add(holder)
        for ep in self._endpoints.values():
            for _ in range(ep.held.pop(holder, 0)):
                ep.concurrency.release()
        for key in [k for k in self._reserved if k[0] == holder]:
            model, bound = self._reserved.pop(key)
            if self.spend is not None:
                self.spend.settle(model, bound, bound)

    def stats(self) -> dict[str, dict[str, Any]]:
        """Per endpoint: slots in use and by whom, the bound, admissions, slots granted and
        the seconds its pause has left (0 outside the board's event loop)."""
        try:
            now: float | None = asyncio.get_running_loop().time()
        except RuntimeError:
            now = None
        return {
            name: {
                "in_flight": ep.concurrency.in_flight,
                "bound": ep.concurrency.bound,
                "held": {h: n for h, n in ep.held.items() if n},
                "admitted": ep.admitted,
                "slots_granted": ep.granted,
                "paused_s": 0.0 if now is None else max(0.0, ep.paused_until - now),
            }
            for name, ep in self._endpoints.items()
        }

    def spent(self) -> dict[str, float]:
        """US dollars per model counted by the spend caps (recorded before plus spent since)."""
        return dict(self.spend.spent) if self.spend is not None else {}


class LimiterActor:
    """The `LimitBoard` as a Ray actor (async: every method runs in the actor's one loop)."""

    def __init__(self, limits: Mapping[str, Mapping[str, Any]], spend: SpendCaps | None = None):
        self.board = LimitBoard(limits, spend)

    async def hold(self, *args: Any) -> CapReached | None:
        return self.board.hold(*args)

    async def settle_spend(self, *args: Any) -> None:
        self.board.settle_spend(*args)

    async def slots(self, endpoint: str, holder: str, want: int, priority: bool) -> Any:
        return await self.board.slots(endpoint, holder, want, priority)

    async def admit(self, endpoint: str, holder: str, estimates: list[float]) -> Any:
        return await self.board.admit(endpoint, holder, estimates)

    async def report(self, *args: Any) -> None:
        self.board.report(*args)

    async def pause(self, endpoint: str, seconds: float) -> None:
        self.board.pause(endpoint, seconds)

    async def forget(self, holder: str) -> None:
        self.board.forget(holder)

    async def stats(self) -> dict[str, dict[str, Any]]:
        return self.board.stats()


class RayChannel:
    """`llm_pool.shared_limits.LimitChannel` to a `LimiterActor` (an actor handle)."""

    def __init__(self, handle: Any):
        self.handle = handle

    async def call(self, method: str, *args: Any) -> Any:
        return await getattr(self.handle, method).remote(*args)

    def send(self, method: str, *args: Any) -> None:
        getattr(self.handle, method).remote(*args)


@dataclass(frozen=True)
class RayBoard:
    """What an engine actor needs to take its limits from the sweep's `LimiterActor`: its
    handle, the endpoints it keeps (names), and whether it keeps the spend caps."""

    handle: Any
    shared: tuple[str, ...]
    capped: bool

    @contextlib.asynccontextmanager
    async def joined(self, holder: str) -> AsyncIterator[BoardLimits]:
        """This engine's `BoardLimits` on the board, as `holder`, for the block (close the pool
        inside it)."""
        limits = BoardLimits(RayChannel(self.handle), holder, self.shared, self.capped)
        try:
            yield limits
        finally:
            await limits.close()


class LocalChannel:
    """`llm_pool.shared_limits.LimitChannel` to a `LimitBoard` in this process's loop (tests)."""

    def __init__(self, board: LimitBoard):
        self.board = board

    async def call(self, method: str, *args: Any) -> Any:
        await asyncio.sleep(0)  # a round trip's worth of interleaving
        answer = getattr(self.board, method)(*args)
        return await answer if asyncio.iscoroutine(answer) else answer

    def send(self, method: str, *args: Any) -> None:
        getattr(self.board, method)(*args)


def shared_endpoints(
    models: Iterable[ModelEndpoint], embedded: Iterable[str]
) -> dict[str, dict[str, Any]]:
    """The limits the board keeps: those of every model not served by the embedded server."""
    return {m.name: m.limits.model_dump() for m in models if m.name not in set(embedded)}


class _BoardReservation:
    def __init__(self, channel: LimitChannel, holder: str, number: int):
        self.channel, self.holder, self.number = channel, holder, number

    def settle(self, cost: float) -> None:
        self.channel.send("settle_spend", self.holder, self.number, float(cost))


class BoardSpend:
    """A process's `LLMPool(spend_caps=...)`: every call's upper bound reserved on the board
    (`llm_pool.spend.Caps`)."""

    def __init__(self, channel: LimitChannel, holder: str):
        self.channel = channel
        self.holder = holder
        self._numbers = 0

    async def reserve(self, model: str, upper_bound: float) -> Reservation | CapReached:
        self._numbers += 1
        number = self._numbers
        try:
            reached = await self.channel.call("hold", self.holder, number, model, upper_bound)
        except asyncio.CancelledError:  # granted or not: nothing of it stays held
            self.channel.send("settle_spend", self.holder, number, 0.0)
            raise
        if reached is not None:
            return reached
        return _BoardReservation(self.channel, self.holder, number)


class BoardLimits:
    """A process's `LLMPool(shared_limits=...)`: the board's limits for the endpoints in
    `shared` (names), the pool's own for the others; with `capped`, the board's spend caps
    (`spend`, for `LLMPool(spend_caps=...)`). `close()` after the pool."""

    def __init__(
        self, channel: LimitChannel, holder: str, shared: Iterable[str], capped: bool = False
    ):
        self.channel = channel
        self.holder = holder
        self.shared = set(shared)
        self.made: list[SharedLimits] = []
        self.spend = BoardSpend(channel, holder) if capped else None

    def __call__(self, endpoint: ModelEndpoint) -> SharedLimits | None:
        if endpoint.name not in self.shared:
            return None
        lim = endpoint.limits
        limits = SharedLimits(
            self.channel,
            endpoint.name,
            self.holder,
            max_concurrency=lim.max_concurrency,
            tpm=lim.tpm,
            period_s=lim.period_s,
        )
        self.made.append(limits)
        return limits

    async def close(self) -> None:
        """Stop asking the board, give back what this process holds, and be forgotten."""
        for limits in self.made:
            await limits.close()
        self.channel.send("forget", self.holder)
