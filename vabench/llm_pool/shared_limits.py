"""Limits shared by several processes.

`SharedLimits` puts one endpoint's limits in one place for several processes (the engines of
a Ray cluster, `limit_board`): a limit board holds the endpoint's `ConcurrencyLimiter`,
`RateLimiter` windows and Retry-After pause, and each process's pool asks it for concurrency
slots and rate admissions through a `LimitChannel`, so N processes never send N times the
allowed rate. The calls of one process that wait at the same moment share one request to the
board (a busy process pays one round trip for many calls, an idle one a round trip per call,
small next to a model call); released slots, successes, token settlements and overloads go
back batched, one message per loop turn, without waiting. Slots are never handed from one
call to the next inside a process: every slot goes back to the board, whose FIFO queue serves
all processes in turn. A pool without `SharedLimits` keeps its own limiters, as before.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Protocol

from vabench.llm_pool.limits import Admission, Slots, check_fits


class LimitChannel(Protocol):
    """How a process reaches the limit board (`limit_board`): `call` awaits the
    board's answer, `send` does not wait (the board applies sends in the order they were
    sent)."""

    async def call(self, method: str, *args: Any) -> Any: ...

    def send(self, method: str, *args: Any) -> None: ...


@dataclass
class _Report:
    """What a process owes the board, sent at the end of the loop turn it was noted in."""

    returned: int = 0
    successes: int = 0
    overloads: int = 0
    settles: list[tuple[int, float]] = field(default_factory=list)


class SharedLimits:
    """One endpoint's limits as kept by a limit board for several processes (see the module
    docstring). `concurrency` and `rate` stand in for the pool's own `ConcurrencyLimiter` and
    `RateLimiter`; `pause(seconds)` tells the board about a Retry-After, which then holds every
    process's next admission. `holder` names this process to the board (its slots are freed
    when the process is gone: `forget`)."""

    def __init__(
        self,
        channel: LimitChannel,
        endpoint: str,
        holder: str,
        *,
        max_concurrency: int,
        tpm: float | None = None,
        period_s: float = 60.0,
    ):
        self.channel = channel
        self.endpoint = endpoint
        self.holder = holder
        self.concurrency = LeasedSlots(self, max_concurrency)
        self.rate = LeasedRate(self, tpm, period_s)
        self._report = _Report()
        self._flush_scheduled = False

    def pause(self, seconds: float) -> None:
        """The endpoint asked for `seconds` of quiet (Retry-After): the board holds every
        process's admissions until then."""
        self.channel.send("pause", self.endpoint, float(seconds))

    def note(
        self,
        *,
        returned: int = 0,
        successes: int = 0,
        overloads: int = 0,
        settle: tuple[int, float] | None = None,
    ) -> None:
        r = self._report
        r.returned += returned
        r.successes += successes
        r.overloads += overloads
        if settle is not None:
            r.settles.append(settle)
        if not self._flush_scheduled:
            self._flush_scheduled = True
            asyncio.get_running_loop().call_soon(self.flush)

    def flush(self) -> None:
        """Send what is owed to the board now."""
        self._flush_scheduled = False
        r, self._report = self._report, _Report()
        if r.returned or r.successes or r.overloads or r.settles:
            counts = (r.returned, r.successes, r.overloads)
            self.channel.send("report", self.endpoint, self.holder, *counts, r.settles)

    async def close(self) -> None:
        """Stop asking the board (calls still waiting for it are cancelled) and send what is
        owed."""
        for fetcher in (self.concurrency, self.rate):
            await fetcher.stop()
        self.flush()


class _Fetcher:
    """The one request to the board a process has out for an endpoint at a time: callers
    queue here, and each request asks for everything queued when it is sent."""

    def __init__(self) -> None:
        self._task: asyncio.Task[None] | None = None

    def _kick(self) -> None:
        if self._task is None or self._task.done():
            self._task = asyncio.get_running_loop().create_task(self._run())

    async def _run(self) -> None:
        try:
            await self._fetch()
        except asyncio.CancelledError:
            self._fail(RuntimeError("the pool was closed while this call waited for its limits"))
            raise
        except Exception as err:  # the board is gone: no caller may wait forever
            self._fail(RuntimeError(f"the limit board did not answer: {err}"))

    async def _fetch(self) -> None:
        raise NotImplementedError

    def _fail(self, err: Exception) -> None:
        raise NotImplementedError

    async def stop(self) -> None:
        if self._task is not None and not self._task.done():
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task


class LeasedSlots(_Fetcher, Slots):
    """The concurrency slots of one endpoint, granted by the board one attempt at a time: the
    pool's `ConcurrencyLimiter` interface (`slot`, `in_flight`, `queued`, `bound`,
    `on_success`, `on_overload`)."""

    def __init__(self, owner: SharedLimits, bound: int):
        super().__init__()
        self._owner = owner
        self._bound = bound
        self.in_flight = 0
        """Slots this process holds now."""
        self._waiters: deque[tuple[asyncio.Future[None], bool]] = deque()

    @property
    def queued(self) -> int:
        return len(self._waiters)

    @property
    def bound(self) -> int:
        """The endpoint's bound across all processes (as the board last said)."""
        return self._bound

    async def acquire(self, *, priority: bool = False) -> None:
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        if priority:
            self._waiters.appendleft((waiter, True))
        else:
            self._waiters.append((waiter, False))
        self._kick()
        try:
            await waiter
        except asyncio.CancelledError:
            if waiter.done() and not waiter.cancelled():
                self.release()  # granted just as we were cancelled
            else:
                self._drop(waiter)
            raise

    def _drop(self, waiter: asyncio.Future[None]) -> None:
        for entry in self._waiters:
            if entry[0] is waiter:
                self._waiters.remove(entry)
                return

    def release(self) -> None:
        self.in_flight -= 1
        self._owner.note(returned=1)

    async def _fetch(self) -> None:
        owner = self._owner
        while self._waiters:
            priority = self._waiters[0][1]
            granted, self._bound = await owner.channel.call(
                "slots", owner.endpoint, owner.holder, len(self._waiters), priority
            )
            if not granted:
                raise RuntimeError(f"the board no longer serves {owner.holder}")
            for _ in range(granted):
                while self._waiters and self._waiters[0][0].done():  # cancelled meanwhile
                    self._waiters.popleft()
                if self._waiters:
                    waiter, _ = self._waiters.popleft()
                    self.in_flight += 1
                    waiter.set_result(None)
                else:  # its caller was cancelled meanwhile
                    owner.note(returned=1)

    def _fail(self, err: Exception) -> None:
        while self._waiters:
            waiter, _ = self._waiters.popleft()
            if not waiter.done():
                waiter.set_exception(err)

    def on_success(self) -> None:
        self._owner.note(successes=1)

    def on_overload(self, now: float) -> None:
        self._owner.note(overloads=1)


class LeasedRate(_Fetcher):
    """The RPM/TPM admissions of one endpoint, granted by the board: the pool's `RateLimiter`
    interface (`check_fits`, `acquire`, `settle`). The board also holds admissions while the
    endpoint's Retry-After pause lasts, so a rate-free endpoint goes through it too."""

    active = True

    def __init__(self, owner: SharedLimits, tpm: float | None, period_s: float):
        super().__init__()
        self._owner = owner
        self._tpm = tpm
        self._period_s = period_s
        self._waiters: deque[tuple[float, asyncio.Future[Admission]]] = deque()

    def check_fits(self, tokens: float) -> None:
        check_fits(tokens, self._tpm, self._period_s)

    async def acquire(self, tokens: float) -> Admission:
        """Wait until the board admits one request of `tokens` estimated tokens. A caller
        cancelled while its admission was being granted leaves it unused (counted, as a
        provider would count a request it never saw: on the safe side)."""
        self.check_fits(tokens)
        waiter: asyncio.Future[Admission] = asyncio.get_running_loop().create_future()
        entry = (float(tokens), waiter)
        self._waiters.append(entry)
        self._kick()
        try:
            return await waiter
        except asyncio.CancelledError:
            if entry in self._waiters:
                self._waiters.remove(entry)
            raise

    async def _fetch(self) -> None:
        owner = self._owner
        loop = asyncio.get_running_loop()
        while self._waiters:
            batch = list(self._waiters)
            granted, lease = await owner.channel.call(
                "admit", owner.endpoint, owner.holder, [tokens for tokens, _ in batch]
            )
            if not granted:
                raise RuntimeError(f"the board no longer serves {owner.holder}")
            now = loop.time()
            for entry in batch[:granted]:
                tokens, waiter = entry
                if entry in self._waiters:
                    self._waiters.remove(entry)
                    if not waiter.done():
                        waiter.set_result(Admission(now, tokens, None, lease=lease))

    def _fail(self, err: Exception) -> None:
        while self._waiters:
            _, waiter = self._waiters.popleft()
            if not waiter.done():
                waiter.set_exception(err)

    def settle(self, admission: Admission, actual_tokens: float) -> None:
        if admission.lease is not None and self._tpm is not None:
            self._owner.note(settle=(admission.lease, actual_tokens - admission.tokens))
        admission.tokens = actual_tokens
