"""The plan of a Ray sweep's engines and the driver's bookkeeping (`ray_executor` runs the sweep,
`ray_driver.ClusterSweep` is its loop): how many engines and what each claims from Ray's
scheduler (`engine_plan`), what an engine's process is started with (`engine_environment`),
the checkout shipped to the cluster (`project_runtime_env`), and the driver's records of a
chunk (`Chunk`) and of an engine (`EngineHandle`).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import vabench
from vabench.config import SweepConfig
from vabench.sim_mjx.warp.device import GPU_SHARE
from vabench.sweep.cells import KeyTuple
from vabench.sweep.choices import Choices, for_engines
from vabench.sweep.runner import critical_path_tasks
from vabench.tuning import mps

CHUNKS_PER_ENGINE = 8
"""Chunks per engine the plan is cut into: enough that engines finish close together."""
SHIPPED = ("vabench", "configs", "assets", "pyproject.toml")
"""What an engine needs of the checkout; every other top-level entry stays home (a second
virtual environment, run directories, caches: one checkout's 1.46 GB `venv/` passed Ray's
512 MiB limit on the package it uploads)."""
SHIP_EXCLUDES = ["__pycache__", "*.pyc", "*.egg-info", ".cache", ".*_cache"]
"""Left out inside what ships."""


def ship_excludes(root: Path) -> list[str]:
    """Ray's `excludes` (gitignore patterns; a leading / anchors at `root`) that leave out every
    top-level entry of `root` but `SHIPPED`, and the caches inside those."""
    others = sorted(p.name for p in root.iterdir() if p.name not in SHIPPED)
    return [f"/{name}" for name in others] + SHIP_EXCLUDES


def project_runtime_env() -> dict[str, Any]:
    """Ray's runtime environment that ships this checkout to the engines (`SHIPPED`), or
    nothing for an installed vabench (then every node has its own)."""
    root = Path(vabench.__file__).resolve().parents[1]
    if not ((root / "pyproject.toml").is_file() and (root / "assets").is_dir()):
        return {}
    return {"working_dir": str(root), "excludes": ship_excludes(root)}


def upload_failure(err: BaseException) -> str:
    """One line for Ray's failure to upload the checkout: its cause (Ray's last line) and the
    fix."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    cause = next((x for x in reversed(lines) if "size" in x.lower()), lines[-1] if lines else "")
    return (
        f"ray: the checkout could not be uploaded to the cluster as the engines' working "
        f"directory: {cause}; move what is not {', '.join(SHIPPED)} out of the checkout, or "
        "install vabench on every node (pip install .) so that nothing is uploaded"
    )


def engine_plan(
    config: SweepConfig, choices: Choices, cluster: Mapping[str, float]
) -> tuple[int, dict[str, float], Choices]:
    """(how many engines, what each claims from Ray's scheduler, the choices they run with) on
    a cluster of `cluster` resources, for a sweep whose command chose `choices` (see
    `ray_executor`'s docstring, 3, and `choices.for_engines`)."""
    asked = config.executor.actors
    gpus = int(cluster.get("GPU", 0))
    engines = for_engines(choices, config, gpus)
    if engines.physics.batched and gpus >= 1:
        # more engines than GPUs: each claims its share of one, so that several engine
        # processes share a GPU under CUDA MPS (one process is paced by its host side)
        n = asked or gpus * engines_per_gpu(config.executor.mps)
        share = 1.0 / math.ceil(n / gpus)  # 1 / engines per GPU: all of them fit
        return n, {"num_cpus": 1.0, "num_gpus": share}, engines
    cpus = 1 + config.render.workers
    resources = {"num_cpus": float(cpus), "num_gpus": 0.0}
    return asked or max(1, int(cluster.get("CPU", 1)) // cpus), resources, engines


def engines_per_gpu(mps_setting: str = "auto") -> int:
    """Engines a GPU when `executor.actors` is unset: `mps.ENGINES_PER_GPU` where they can share
    it under CUDA MPS (`mps_setting`, the config's `executor.mps`, is auto and NVIDIA's control
    program is on this node, which stands for the cluster's: nodes of one image; an engine on a
    node without it warns and its GPU's engines take turns), else one. Measured on 2 x H200
    (2026-11-29, the base families' 1,120 episodes): four a GPU 134.2 s on one GPU and 86.6 s
    on two, one a GPU 190.3 s and 125.2 s: 1.42x and 1.45x (docs/PERFORMANCE.md, Ray, "Two
    NVIDIA H200 of one host")."""
    if mps_setting == "auto" and mps.control_program() is not None:
        return mps.ENGINES_PER_GPU
    return 1


def engine_environment(
    config: SweepConfig, cores: int, gpu_share: int = 1, sweep: str = "", ranked: bool = False
) -> dict[str, str]:
    """What an engine's process is started with: the config's API keys from this process's
    environment, `VABENCH_CORES` (the engine's share of its node, which sizes the embedded
    server's policy processes) and, where engines share a GPU, `VABENCH_GPU_SHARE` (how many:
    GPU buffers sized from the memory free take that share of it) and, unless `executor.mps` is
    off, the sweep's id `sweep` as `mps.NODE_SWEEP`: the engines of a node join one CUDA MPS
    daemon of the sweep's, so that their kernels run side by side instead of their contexts
    taking turns (one engine process is paced by its host side: on 4 x H100, 2026-11-28, an
    engine's GPU was 23-35 % busy; the local sweep runs 4 processes a GPU under MPS). `ranked`
    (the sweep has critical chunks): `mps.NODE_RANKED` too, so that one engine a GPU is a
    normal MPS client for them and the others below normal."""
    env = {"VABENCH_CORES": str(max(1, cores))}
    if gpu_share > 1:
        env[GPU_SHARE] = str(gpu_share)
        if config.executor.mps == "auto" and sweep:
            env[mps.NODE_SWEEP] = sweep
            if ranked:
                env[mps.NODE_RANKED] = "1"
    for model in config.models:
        name = model.api_key_env
        if name and os.environ.get(name):
            env[name] = os.environ[name]
    return env


def with_critical_path(choices: Choices, budgets: Mapping[str, int]) -> Choices:
    """The engines' `choices` with the whole sweep's critical path (`runner.critical_path_tasks`
    over every task's step budget, `budgets`): each chunk runs in a `LocalSweep` of its own
    tasks, and the basket's chunks, alone, would find nothing to stand out from (so its batches
    never had the GPU's highest stream priority; the same was found in the processes executor
    on an H100, 2026-11-27)."""
    critical = tuple(sorted(critical_path_tasks(dict(budgets))))
    return replace(choices, executor=replace(choices.executor, critical_path=critical))


@dataclass
class Chunk:
    name: str
    keys: list[KeyTuple]
    cost: int
    """Of one episode (the task's step budget)."""
    critical: bool = False
    """Of a task on the sweep's critical path (`runner.critical_path_tasks`: the basket): it
    runs alone in its engine, one such chunk a GPU where the engines allow (`choose_engine`)."""


START_GRACE_S = 300.0
"""How long an engine still starting holds a fair share of the plan (`choose_engine`): one that
never starts (its resources held elsewhere, a node that never comes) must not keep the ready
engines below their share for the whole sweep."""


CRITICAL_WAIT_S = 60.0
"""How long after the sweep's first engine was asked for a critical chunk may wait for engines
still starting (they may sit on a GPU without a critical chunk) before it takes an idle engine
on a GPU that has one (`choose_engine`)."""


def choose_engine(
    engines: list[EngineHandle],
    chunk: Chunk,
    records: Mapping[KeyTuple, Any],
    queued_cost: int,
    max_chunks: int,
    now: float | None = None,
) -> EngineHandle | None:
    """The engine the queue's next `chunk` goes to, or None for none now.

    A chunk off the critical path (`queued_cost`: the cost of the queue's other such chunks)
    goes to the least loaded (cost of its episodes given and not yet recorded) of the ready
    engines with room that hold no critical chunk (where some live engine holds none). Room:
    an engine without chunks always has some. One with chunks takes another only while (1) it
    holds fewer than `max_chunks` chunks and fewer episodes than twice its in-flight limit, and
    (2) its load with the chunk stays within its fair share, the unfinished cost off the
    critical path (`queued_cost` plus those engines' loads) over the live engines holding no
    critical chunk, those still starting included for their first `START_GRACE_S` (monotonic
    `now`). Without (2) the first engine ready took every chunk up to its limit (2 x 1,024
    episodes): on 4 x H100 (2026-11-27) two engines ran all 14 families of a 168-episode plan
    while two started later and got none (0.26 of 4x one engine). With it a chunk left over
    waits in the queue for whichever engine's load falls first.

    A critical chunk (`Chunk.critical`, the basket's) goes to an idle engine, where there is
    one and another live engine for the rest of the plan, on the GPU with the fewest critical
    chunks; while none is idle on a GPU without one and engines are still starting (in the
    sweep's first `CRITICAL_WAIT_S`), it waits for them; with no idle engine it is placed like
    any other. Its engine then takes nothing else until it is done. On 4 x H200 (2026-11-28) one
    engine worked 168 s on three chunks, the basket's among them, at ~0.93 s for each of the
    basket's ~181 decisions, on the busiest of the four GPUs, while the other 15 engines had
    finished 50-120 s earlier: the basket's chain is the sweep's."""
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
    own = len(chunk.keys) * chunk.cost if chunk.critical else 0  # not in `queued_cost`
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
    """For a critical chunk: an idle ready engine on the GPU with the fewest critical chunks,
    its GPU's lead (`EngineHandle.lead`: the normal MPS priority) before the others; `WAIT`
    while engines are still starting in the sweep's first `CRITICAL_WAIT_S` (from `since`, its
    first engine's request: a replacement engine later is not waited for) and may offer a GPU
    without one, or its lead (a lead ready and busy is not waited for); or None (no idle
    engine: the ordinary rule places it). A chunk placed on a below-normal engine after the
    wait runs behind its GPU's lead (the driver's log says so): the wait counts from the
    sweep's first request, so that a lead slow to start costs at most a minute."""
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
    records: Mapping[KeyTuple, Any],
    max_chunks: int,
    now: float | None = None,
) -> tuple[int, EngineHandle] | None:
    """The driver's next hand-out: (the chunk's position in `queue`, its engine), or None for
    none now. The queue's chunks in order (costliest first): a critical chunk waiting for
    engines still starting (`choose_engine`) is passed over, so that the ready engines take
    the chunks behind it meanwhile; the first other chunk without an engine ends the hand-out."""
    queued = sum(len(c.keys) * c.cost for c in queue if not c.critical)
    for i, chunk in enumerate(queue):
        best = choose_engine(engines, chunk, records, queued, max_chunks, now)
        if best is not None:
            return i, best
        if not chunk.critical:
            return None
    return None


@dataclass
class EngineClock:
    """An engine's time as the driver sees it (monotonic seconds): asked for, started, ended
    (died, or the sweep closed it), and the seconds it had at least one chunk ("working"); the
    rest of its started life it waited for work. The split tells a scaling run where lost
    engine-time went: start-up, waiting for work (placement, the tail), or working slower."""

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
    """The driver's view of one engine actor."""

    index: int
    actor: Any
    holder: str
    starting: Any
    """The `start()` reference until the engine has started."""
    info: dict[str, Any] = field(default_factory=dict)
    chunks: dict[Any, Chunk] = field(default_factory=dict)
    """Chunks running there, by their stream."""
    status: dict[str, Any] = field(default_factory=dict)
    status_ref: Any = None
    dead: bool = False
    clock: EngineClock = field(default_factory=EngineClock)
    final: dict[str, Any] = field(default_factory=dict)
    """What its `close()` returned (its GPU's busy share over its life)."""
    given: list[Chunk] = field(default_factory=list)
    """Every chunk it was given, in order (the scaling report's placement)."""

    @property
    def ready(self) -> bool:
        return self.starting is None and not self.dead

    @property
    def lead(self) -> bool:
        """Whether its MPS priority is normal: its GPU's first engine of a ranked sweep
        (`mps.NODE_RANKED`), or any engine where priorities are not ranked (or before it has
        started)."""
        environment = self.info.get("environment") or {}
        return environment.get(mps.PRIORITY_VARIABLE) != mps.BELOW_NORMAL

    @property
    def gpu(self) -> Any:
        """Which GPU it runs on (its node and Ray's GPU ids, once started; else itself)."""
        gpus = self.info.get("gpus")
        return (self.info.get("node"), tuple(gpus)) if gpus else ("engine", self.index)

    def unfinished(self, records: Mapping[KeyTuple, Any]) -> tuple[int, int]:
        """(episodes given and not recorded, their cost)."""
        n = cost = 0
        for chunk in self.chunks.values():
            left = sum(k not in records for k in chunk.keys)
            n += left
            cost += left * chunk.cost
        return n, cost
