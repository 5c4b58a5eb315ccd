"""Where the driver sends the queue's next chunk: the driver's records of a chunk (`Chunk`) and
of an engine (`EngineHandle`, with its clock), and the placement rule (`next_placement`,
`choose_engine`), the same for worker processes and Ray actors.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import Key, ledger_key
from vabench.tuning import mps


@dataclass
class Chunk:
    name: str
    keys: list[EpisodeKey]
    cost: float
    """Of one episode (`cells.episode_costs`: measured seconds, else the step budget)."""
    critical: bool = False
    """Of a task on the sweep's critical path (`cells.critical_path_tasks`: the basket): it
    runs alone in its engine, one such chunk a GPU where the engines allow (`choose_engine`)."""


class Engine(Protocol):
    """The driver's handle on one engine; each call returns at once, its outcome an event."""

    def start(self, tasks: Sequence[str]) -> None:
        """Open the engine (compiling the kernels of `tasks` ahead): STARTED, or LOST."""

    def run_chunk(self, chunk: Chunk) -> None:
        """Run `chunk`: its LINE events, then DONE or FAILED (or the engine's LOST)."""

    def close(self) -> None:
        """Close the engine: CLOSED with its figures."""

    def kill(self) -> None:
        """End it at once; lines it sent before come first."""


START_GRACE_S = 300.0
"""How long an engine still starting holds a fair share of the plan (`choose_engine`): one that
never starts (a node that never comes) must not keep the ready engines below their share."""
CRITICAL_WAIT_S = 60.0
"""How long from the sweep's first engine request a critical chunk may wait for engines still
starting (maybe on a GPU without one) before it takes an idle engine on a GPU that has one."""


@dataclass
class EngineClock:
    """An engine's time as the driver sees it (monotonic seconds): asked for, started, ended, and
    the seconds it held a chunk ("working"), the rest waiting: a scaling run's split of where
    lost engine-time went (start-up, placement and the tail, or working slower)."""

    asked_at: float = field(default_factory=time.monotonic)
    started_at: float | None = None
    ended_at: float | None = None
    working_since: float | None = None
    working_s: float = 0.0
    episodes: int = 0
    """Ledger lines its chunks reported."""

    def work_began(self, now: float) -> None:
        if self.working_since is None:
            self.working_since = now

    def work_ended(self, now: float) -> None:
        if self.working_since is not None:
            self.working_s += now - self.working_since
            self.working_since = None

    def end(self, now: float) -> None:
        if self.ended_at is None:
            self.work_ended(now)
            self.ended_at = now

    def figures(self, now: float) -> dict[str, float]:
        """Seconds of start-up (asked for to started, or to its end if it never started),
        working and waiting for work, up to its end (or `now`)."""
        end = self.ended_at if self.ended_at is not None else now
        since = self.working_since
        working = self.working_s + (end - since if since is not None else 0.0)
        started = self.started_at if self.started_at is not None else end
        return {
            "start_up_s": started - self.asked_at,
            "working_s": working,
            "waiting_s": max(end - started - working, 0.0),
            "life_s": end - self.asked_at,
        }


@dataclass
class EngineHandle:
    """The driver's view of one engine (`Engine`: a worker process or a Ray actor)."""

    index: int
    engine: Engine | None = None
    """The worker process or actor it drives."""
    slot: int = 0
    """The place in the plan it fills (an engine started for a dead one takes its slot)."""
    starting: bool = True
    """Until its start has been reported."""
    info: dict[str, Any] = field(default_factory=dict)
    chunks: dict[str, Chunk] = field(default_factory=dict)
    """Chunks running there, by name."""
    status: dict[str, Any] = field(default_factory=dict)
    dead: bool = False
    clock: EngineClock = field(default_factory=EngineClock)
    final: dict[str, Any] = field(default_factory=dict)
    """What its close returned (its GPU's busy share over its life)."""
    given: list[Chunk] = field(default_factory=list)
    """Every chunk it was given, in order (the scaling report's placement)."""

    @property
    def ready(self) -> bool:
        return not self.starting and not self.dead

    @property
    def lead(self) -> bool:
        """Whether its MPS priority is normal: its GPU's first engine of a ranked sweep
        (`mps.NODE_RANKED`), or any engine where priorities are not ranked or not yet known."""
        environment = self.info.get("environment") or {}
        return environment.get(mps.PRIORITY_VARIABLE) != mps.BELOW_NORMAL

    @property
    def gpu(self) -> Any:
        """Which GPU it runs on (its node and GPU ids, once started; else itself)."""
        gpus = self.info.get("gpus")
        return (self.info.get("node"), tuple(gpus)) if gpus else ("engine", self.index)

    def unfinished(self, records: Mapping[Key, Any]) -> tuple[int, float]:
        """(episodes given and not recorded, their cost)."""
        n, cost = 0, 0.0
        for chunk in self.chunks.values():
            left = sum(ledger_key(k) not in records for k in chunk.keys)
            n += left
            cost += left * chunk.cost
        return n, cost


def choose_engine(
    engines: list[EngineHandle],
    chunk: Chunk,
    records: Mapping[Key, Any],
    queued_cost: float,
    max_chunks: int,
    now: float | None = None,
) -> EngineHandle | None:
    """The engine the queue's next `chunk` goes to, or None for none now.

    A chunk off the critical path goes to the least loaded (cost given and not yet recorded) of
    the ready engines with room that hold no critical chunk (where some live engine holds none).
    An engine without chunks has room; one with chunks only while it holds fewer than
    `max_chunks` chunks and fewer episodes than twice its in-flight limit, and its load with the
    chunk stays within a fair share: the unfinished cost off the critical path (`queued_cost`,
    the queue's other such chunks, plus those engines' loads) over those engines, the ones still
    starting counted for their first `START_GRACE_S` (monotonic `now`). Without the share the
    first engine ready takes every chunk; with it a leftover waits for the first load to fall.

    A critical chunk (`Chunk.critical`) goes where `_critical_engine` says, else like any other;
    its engine then takes nothing else until it is done: its chain of decisions is the sweep's
    and must not wait behind other batches."""
    now = time.monotonic() if now is None else now
    live = [
        e for e in engines if not e.dead and (e.ready or now - e.clock.asked_at < START_GRACE_S)
    ]
    holding = {id(e) for e in live if any(c.critical for c in e.chunks.values())}
    if chunk.critical:
        since = min((e.clock.asked_at for e in engines), default=now)
        placed = _critical_engine(live, holding, now, since)
        if placed is not None:
            return placed if isinstance(placed, EngineHandle) else None
    sharing = [e for e in live if id(e) not in holding] or live
    loads = {id(e): e.unfinished(records) for e in live}
    own = len(chunk.keys) * chunk.cost if chunk.critical else 0.0  # not in `queued_cost`
    share = (queued_cost + own + sum(loads[id(e)][1] for e in sharing)) / max(1, len(sharing))
    best: EngineHandle | None = None
    for e in sharing:
        if not e.ready or len(e.chunks) >= max_chunks:
            continue
        left, cost = loads[id(e)]
        if e.chunks:
            room = 2 * max(1, int(e.status.get("limit", 1)))
            if left >= room or cost + len(chunk.keys) * chunk.cost > share:
                continue
        if best is None or cost < loads[id(best)][1]:
            best = e
    return best


WAIT = object()
"""`_critical_engine`: the critical chunk waits for engines still starting."""


def _critical_engine(
    live: list[EngineHandle], holding: set[int], now: float, since: float
) -> EngineHandle | object | None:
    """For a critical chunk, where another live engine is left for the rest of the plan: an idle
    ready engine on the GPU with the fewest critical chunks, its GPU's lead (`EngineHandle.lead`)
    first; `WAIT` while engines still starting in the sweep's first `CRITICAL_WAIT_S` (from
    `since`: a later replacement is not waited for) may offer a GPU without one, or its lead (a
    lead ready and busy is not waited for); None with no idle engine (the ordinary rule)."""
    if len(live) - len(holding) < 2:  # none would be left for the rest of the plan
        return None
    on_gpu: dict[Any, int] = {}
    for e in live:
        if id(e) in holding:
            on_gpu[e.gpu] = on_gpu.get(e.gpu, 0) + 1
    idle = [e for e in live if e.ready and not e.chunks]
    best = min(idle, key=lambda e: (on_gpu.get(e.gpu, 0), not e.lead, e.index)) if idle else None
    # a GPU's lead already working (on other chunks) is not waited for: it stays busy
    if (
        best is not None
        and on_gpu.get(best.gpu, 0) == 0
        and (best.lead or any(e.ready and e.lead and e.gpu == best.gpu for e in live))
    ):
        return best
    if now - since < CRITICAL_WAIT_S and any(not e.ready for e in live):
        return WAIT
    return best


def next_placement(
    engines: list[EngineHandle],
    queue: Sequence[Chunk],
    records: Mapping[Key, Any],
    max_chunks: int,
    now: float | None = None,
) -> tuple[int, EngineHandle] | None:
    """The driver's next hand-out: (the chunk's position in `queue`, its engine), or None. A
    critical chunk waiting for engines still starting is passed over, so that the ready engines
    take the chunks behind it meanwhile; the first other chunk without an engine ends it."""
    queued = sum(len(c.keys) * c.cost for c in queue if not c.critical)
    for i, chunk in enumerate(queue):
        best = choose_engine(engines, chunk, records, queued, max_chunks, now)
        if best is not None:
            return i, best
        if not chunk.critical:
            return None
    return None
