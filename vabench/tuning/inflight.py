"""How many episodes one sweep process keeps in flight: enough to keep the simulator, the
renderer and the model endpoints busy, and no more.

An episode is a chain of decisions, each waiting on the renderer, a model endpoint and the
simulator. With N episodes in flight and a decision taking R seconds, decisions complete at
X = N / R per second (Little's law). While no stage is saturated, R stays at its unloaded value
R0 and X grows with N; once one stage saturates, X stops growing and every further episode only
lengthens the queues: R grows as N / X_max. Too few wastes the machine; too many makes every
episode slow and the first one finish late (256 episodes in lockstep on a 2-core laptop: none
finished in 10 minutes, all of them near their end together).

`LimitController` sets N from the decisions' own timing, as TCP Vegas and Netflix's
concurrency-limits (gradient2) do. Each kind of decision (model, protocol, task) has a baseline
R0, the best median time a window of its decisions ever showed: its unloaded time. Once a window
of decisions has completed (at least half the episodes in flight, and `MIN_WINDOW`), the
controller takes the median of their times relative to their baselines, the stretch R / R0,
and sets, with n the most episodes in flight during the window,

    limit <- n + sqrt(n)                          while stretch <= TOLERANCE
    limit <- n * max(0.5, TOLERANCE / stretch)    past it

Below the knee the stretch is about 1 and the limit grows by sqrt(n) a window; past it,
R = n / X_max, and the limit settles where decisions take about `TOLERANCE` times their
unloaded time: every stage busy, a short queue. The tolerance also absorbs a baseline caught
in a lucky moment. It starts at one episode (so R0 is measured unloaded) and doubles each window
until the first window past the tolerance (slow start). `InFlight` is the asyncio gate episodes
pass through; `reason` says why the limit is what it is (the display shows it).

Batched physics (MuJoCo Warp, MJX) is the exception: one step of the batch costs about the same
for one acting slot as for all of them, so the only way to use it is to fill it, and a
decision's time measures the other processes sharing the GPU more than this one's load (16
sweep processes sharing one GPU, held at 1-2 episodes each by this controller, made a few
decisions a second). There
`auto` holds the ceiling (`BATCHED`).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import math
import statistics
from collections.abc import AsyncIterator, Hashable
from dataclasses import dataclass

MIN_WINDOW = 4
"""Fewest decisions a window needs before the limit moves."""
TOLERANCE = 1.5
"""How much longer than unloaded a decision may take before the limit stops growing."""
MIN_GRADIENT = 0.5
"""The most one window may shrink the limit (halving), so one noisy window cannot empty it."""


BATCHED = "batched physics: every slot of a step costs the same, so all the batch's episodes"


class LimitController:
    """The limit, from the times of completed decisions (see the module docstring)."""

    def __init__(
        self, ceiling: int, fixed: int | None = None, initial: int = 1, why: str | None = None
    ):
        """`fixed`: hold that many (`why` says why; default: the config asked for it)."""
        if ceiling < 1:
            raise ValueError(f"ceiling must be >= 1, got {ceiling}")
        self.ceiling = ceiling
        self.fixed = fixed
        self.windows = 0
        if fixed is not None:
            self.limit = max(1, min(fixed, ceiling))
            self.reason = (why or f"executor.in_flight = {fixed}") + (
                f", capped by executor.max_episodes = {ceiling}" if fixed > ceiling else ""
            )
            return
        self.limit = max(1, min(initial, ceiling))
        self.reason = "starting with one episode to time an unloaded decision"
        self.slow_start = True
        self.best: dict[Hashable, float] = {}
        self._window: list[tuple[Hashable, float]] = []
        self._busiest = 0

    def observe(self, kind: Hashable, seconds: float, in_flight: int | None = None) -> bool:
        """One decision of `kind` completed in `seconds` with `in_flight` episodes in flight
        (default: the limit); True when the limit changed."""
        if self.fixed is not None:
            return False
        self._window.append((kind, seconds))
        self._busiest = max(self._busiest, self.limit if in_flight is None else in_flight)
        if len(self._window) < max(MIN_WINDOW, self._busiest // 2):
            return False
        window, self._window = self._window, []
        busiest, self._busiest = max(1, self._busiest), 0
        self.windows += 1
        for k in {k for k, _ in window}:
            own = statistics.median(s for kk, s in window if kk == k)
            self.best[k] = min(self.best.get(k, math.inf), own)
        stretch = statistics.median(s / self.best[k] for k, s in window)
        before = self.limit
        if self.slow_start and stretch <= TOLERANCE:
            self.limit = min(self.ceiling, busiest * 2)
            self.reason = f"decisions at {stretch:.2f}x their unloaded time: doubling"
        else:
            self.slow_start = False
            gradient = max(MIN_GRADIENT, min(1.0, TOLERANCE / stretch))
            # below the tolerance, grow by sqrt(n); past it, shrink to where it would be met
            wanted = busiest + math.sqrt(busiest) if gradient >= 1.0 else busiest * gradient
            self.limit = max(1, min(self.ceiling, int(wanted)))
            self.reason = f"decisions at {stretch:.2f}x their unloaded time: " + (
                "growing" if gradient >= 1.0 else "a stage is saturated"
            )
        if self.limit == self.ceiling:
            self.reason += f" (at executor.max_episodes = {self.ceiling})"
        return self.limit != before


class InFlight:
    """The asyncio gate: `async with gate.slot():` around an episode; `observe` after each of
    its decisions. Waiters are admitted in arrival order."""

    def __init__(
        self, ceiling: int, fixed: int | None = None, initial: int = 1, why: str | None = None
    ):
        self.controller = LimitController(ceiling, fixed, initial, why)
        self.in_flight = 0
        self.peak = 0
        self._waiters: collections.deque[asyncio.Future[None]] = collections.deque()

    @property
    def limit(self) -> int:
        return self.controller.limit

    @property
    def reason(self) -> str:
        return self.controller.reason

    def observe(self, kind: Hashable, seconds: float) -> None:
        if self.controller.observe(kind, seconds, self.in_flight):
            self._admit()

    @contextlib.asynccontextmanager
    async def slot(self) -> AsyncIterator[None]:
        await self._acquire()
        try:
            yield
        finally:
            self.in_flight -= 1
            self._admit()

    async def _acquire(self) -> None:
        if not self._waiters and self.in_flight < self.limit:
            self._enter()
            return
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._waiters.append(future)
        try:
            await future
        except asyncio.CancelledError:
            if future.done() and not future.cancelled():  # admitted, then cancelled: give back
                self.in_flight -= 1
                self._admit()
            else:
                with contextlib.suppress(ValueError):
                    self._waiters.remove(future)
            raise

    def _enter(self) -> None:
        self.in_flight += 1
        self.peak = max(self.peak, self.in_flight)

    def _admit(self) -> None:
        while self._waiters and self.in_flight < self.limit:
            future = self._waiters.popleft()
            if not future.done():
                self._enter()
                future.set_result(None)


@dataclass(frozen=True)
class InFlightRule:
    """How many episodes one sweep process keeps in flight: the ceiling
    (`executor.max_episodes`), and either a number held (`fixed`, `why` it is held) or none
    (adapt, `LimitController`). `in_flight_rule` makes it; `--dry-run` prints `describe()`
    and every sweep process gates its episodes with `gate()`."""

    ceiling: int
    fixed: int | None = None
    why: str | None = None
    """Why `fixed` is held when the config did not ask for it (`BATCHED`)."""

    def describe(self) -> str:
        if self.fixed is None:
            return (
                f"adaptive, at most {self.ceiling} episodes per process (executor.in_flight: "
                "enough to keep simulator, renderer and endpoints busy without queueing)"
            )
        if self.why is not None:
            return f"{min(self.fixed, self.ceiling)} episodes per process at most ({self.why})"
        return f"{min(self.fixed, self.ceiling)} episodes per process (asked for)"

    def gate(self) -> InFlight:
        return InFlight(self.ceiling, self.fixed, why=self.why)


def in_flight_rule(in_flight: int | str, max_episodes: int, batched: bool) -> InFlightRule:
    """The in-flight rule of `executor.in_flight` ("auto" or a number) and
    `executor.max_episodes` for physics that is `batched` or not (see the module docstring)."""
    if isinstance(in_flight, int):
        return InFlightRule(max_episodes, in_flight)
    if batched:
        return InFlightRule(max_episodes, max_episodes, BATCHED)
    return InFlightRule(max_episodes)
