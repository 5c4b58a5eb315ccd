"""Running a planned sweep in one process: every task batch of the plan concurrently, resumable.

One asyncio loop holds the `Engine` (`open_engine`: the LLM pool, the embedded server, one
renderer, the in-flight gate) and up to `executor.max_tasks` task batches at once, each serving
every model and track of its task. `LocalSweep` resumes from the ledger (a recorded episode never
runs again, an orphaned result.json is adopted), waits for each family's learning session,
re-runs infrastructure failures for `retries.infrastructure_rounds` rounds, and stops at a fatal
endpoint refusal, a spend cap or a failed GPU, recording nothing of what that stopped
(docs/RELIABILITY.md lists each promise and its test).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import defaultdict
from collections.abc import AsyncIterator, Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from vabench.agent.engine import EpisodeSpec, run_episode
from vabench.agent.learning import LearningLimits
from vabench.agent.learning_stage import SummaryStage, unavailable_result
from vabench.agent.records import EpisodeResult
from vabench.agent.services import task_services
from vabench.config import SweepConfig
from vabench.config.choices import Choices
from vabench.llm_pool.config import ModelEndpoint
from vabench.llm_pool.errors import RequestRejected, SpendCapReached
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer
from vabench.llm_pool.shared_limits import SharedLimits
from vabench.llm_pool.spend import Caps, SpendCaps
from vabench.render.backends import Renderer, make_renderer
from vabench.render.images import ImageSettings
from vabench.report.spend import recorded_spend
from vabench.sim_mjx.backends import Choice
from vabench.sim_mjx.interface import DeviceFailure, device_failure
from vabench.sim_mjx.warp.device import warp_device
from vabench.sweep.cells import sweep_critical_path
from vabench.sweep.display import Counts
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import Ledger, Sink, ledger_key, recover, set_aside
from vabench.tasks import get_task
from vabench.tuning import hostload
from vabench.tuning.inflight import InFlight
from vabench.tuning.precompile import Compiling

log = logging.getLogger(__name__)


class SweepStopped(Exception):
    """An endpoint, a spend cap or the GPU stopped the sweep (`LocalSweep.stopped` says which
    and why); raised by the executors once every chunk in flight has ended."""


@dataclass
class SweepProgress:
    """Live counters per (model, track, task): the episodes running and those re-run after an
    infrastructure error (the engine's status and its chunk's summary)."""

    cells: dict[tuple[str, str, str], Counts] = field(default_factory=lambda: defaultdict(Counts))

    def total(self) -> Counts:
        return Counts.total(self.cells.values())


@dataclass
class Engine:
    """What one sweep process holds while it runs episodes, shared by every task batch it
    runs: the resolved physics, the LLM pool (and the embedded server behind it), the learning
    stage, the renderer and the in-flight gate. `open_engine` opens one."""

    physics: Choice
    llm: LLMPool
    summaries: SummaryStage
    renderer: Renderer
    image: ImageSettings
    gate: InFlight


@contextlib.asynccontextmanager
async def open_engine(
    config: SweepConfig,
    choices: Choices,
    run_dir: Path,
    *,
    shared_limits: Callable[[ModelEndpoint], SharedLimits | None] | None = None,
    spend_caps: Caps | None = None,
) -> AsyncIterator[Engine]:
    """The engine of `config` on `choices` for episodes of `run_dir`, open for the block.
    `shared_limits`, `spend_caps`: `LLMPool(shared_limits=..., spend_caps=...)` (limits and
    spend caps kept for several processes, by the limit board)."""
    gate = choices.in_flight.gate()
    async with contextlib.AsyncExitStack() as stack:
        # The renderer starts (its device, its modules, GL's processes) while the embedded
        # server's processes start: each takes seconds of an engine's start-up.
        render = config.render
        renderer, _choice = make_renderer(
            choices.renderer,
            workers=render.workers,
            platform=render.platform,
            max_size=(render.width, render.height),
        )
        starting = asyncio.ensure_future(asyncio.to_thread(renderer.start))

        async def close_renderer() -> None:
            await asyncio.wait({starting})  # a start still running in its thread ends first
            if not starting.cancelled():
                starting.exception()  # raised below, or moot beside the error unwinding this
            renderer.close()

        stack.push_async_callback(close_renderer)
        endpoints = list(config.models)
        if config.embedded_models:
            server = await stack.enter_async_context(LocalServer(config.embedded_server))
            endpoints = config.endpoints(server.base_url)
            log.info(
                "embedded server on %s, served %s",
                server.url,
                f"by {server.processes} processes" if server.processes else "in this process",
            )
        pool = LLMPool(endpoints, shared_limits=shared_limits, spend_caps=spend_caps)
        llm = await stack.enter_async_context(pool)
        summaries = SummaryStage(
            run_dir,
            llm,
            demo_cache=config.learning.cache_path(),
            limits=LearningLimits(max_model_calls=config.learning.max_model_calls),
        )
        info = await starting
        log.info("renderer started: %s", info)  # the choice and its reason: a start line
        yield Engine(choices.physics, llm, summaries, renderer, render.image_settings(), gate)


def compile_ahead(
    tasks: Iterable[str], choices: Choices, size: tuple[int, int], first: Collection[str] = ()
) -> Compiling | None:
    """Warp physics on a GPU: the kernels of every family of `tasks` (images of `size`)
    compiled side by side in the background (`precompile.Compiling`; nothing to do once they
    are; engines of one machine wait for each other's compiling through its lock), each
    family's episodes waiting only for its own kernels, those of `first` (the sweep's critical
    path) ahead of the others; None where nothing compiles."""
    tasks = sorted(set(tasks))
    if not tasks or not choices.physics.is_warp or not warp_device().startswith("cuda"):
        return None
    return Compiling.start(tasks, *size, warp_device(), choices.renderer.is_warp, first)


async def start_compiling(
    engine: Engine, choices: Choices, tasks: Iterable[str], first: Collection[str] = ()
) -> Compiling | None:
    """`compile_ahead` for `engine`'s images, in a thread."""
    size = (engine.image.width, engine.image.height)
    return await asyncio.to_thread(compile_ahead, tasks, choices, size, first)


class LocalSweep:
    """Runs `keys` of `config` into `run_dir` on `choices` (see the module docstring)."""

    def __init__(
        self,
        config: SweepConfig,
        keys: Sequence[EpisodeKey],
        run_dir: Path,
        choices: Choices,
        ledger_sink: Sink | None = None,
    ):
        self.config = config
        self.choices = choices
        self.keys = list(keys)
        self.run_dir = run_dir
        self.ledger = Ledger.open(run_dir, sink=ledger_sink)
        for line in self.ledger.collapsed:
            log.warning("ledger: %s", line)
        self.progress = SweepProgress()
        self.stopped: str | None = None
        """Why the sweep stopped early (an endpoint refused it), naming model and fix."""
        self.device_failed = False
        """`stopped` because this process's GPU context failed (a new process may go on)."""
        self.capped: dict[str, str] = {}
        """Models whose `limits.max_cost_usd` stopped their calls: model -> which cap, at what
        spend (the sweep's own cap sets `stopped` instead)."""
        self.gate: InFlight | None = None
        """The engine's, once `run` has one."""
        self.physics: Choice | None = None
        self.compiling: Compiling | None = None
        """This sweep's families' kernels compiling in the background (Warp on a GPU)."""

    # -- bookkeeping ---------------------------------------------------------------------------
    def _adopt_orphans(self) -> None:
        """Episodes whose result.json was written but not recorded (a kill in between)."""
        for k in self.keys:
            if self.ledger.finished(ledger_key(k)):
                continue
            result = recover(self.run_dir, k.rel_dir)
            if result is None:
                continue
            if result.status == "infrastructure_error":
                self.ledger.add_infrastructure_failure(k.track, k.rel_dir, result)
                set_aside(self.run_dir / k.rel_dir)
            else:
                self.ledger.add(k.track, k.rel_dir, result)

    def _pending(self) -> list[EpisodeKey]:
        rounds = self.config.retries.infrastructure_rounds
        return [
            k
            for k in self.keys
            if not self.ledger.finished(ledger_key(k))
            and self.ledger.infra_attempts[ledger_key(k)] <= rounds
            and k.model not in self.capped
        ]

    # -- running -------------------------------------------------------------------------------
    async def run(self, engine: Engine | None = None) -> SweepProgress:
        """Run the planned episodes, in `engine` (kept open by the caller, shared with other
        sweeps: a Ray engine actor) or in one opened for this run."""
        self._adopt_orphans()
        async with hostload.watching():
            if engine is not None:
                await self._run_in(engine)
            else:
                async with open_engine(self.config, self.choices, self.run_dir) as own:
                    await self._run_in(own)
        return self.progress

    async def _run_in(self, engine: Engine) -> None:
        self.physics, self.gate, self.summaries = engine.physics, engine.gate, engine.summaries
        if not engine.llm.shared_spend:  # else the limit board keeps them for every process
            engine.llm.set_spend_caps(spend_caps(self.config, self.run_dir))
        tasks = {k.task for k in self._pending()}  # their kernels compiled in the background
        budgets = {name: self.config.budget(name) for name in tasks}
        first = sweep_critical_path(self.choices.executor.critical_path, budgets)
        self.compiling = await start_compiling(engine, self.choices, tasks, first)
        round_no = 0
        while (pending := self._pending()) and self.stopped is None:
            if round_no:
                self.summaries.forget_failures()
                log.warning(
                    "retry round %d: %d episodes after infrastructure errors",
                    round_no,
                    len(pending),
                )
            await self._run_round(pending, engine)
            round_no += 1
        if self.capped and self.stopped is None:
            self.stopped = (
                "; ".join(self.capped.values())
                + f". No call of {'that model' if len(self.capped) == 1 else 'those models'} "
                "was started past it; the episodes it stopped or never started have no record. "
                "Raise the cap and run the same command to resume."
            )
            log.error("stopped: %s", self.stopped)

    async def _run_round(self, keys: list[EpisodeKey], engine: Engine) -> None:
        by_task: dict[str, list[EpisodeKey]] = defaultdict(list)
        for k in keys:
            by_task[k.task].append(k)
        task_gate = asyncio.Semaphore(self.choices.executor.max_tasks)

        async def one_task(name: str, task_keys: list[EpisodeKey], critical: bool) -> None:
            if self.compiling is not None:  # its kernels, not every family's
                await self.compiling.wait(name)
            async with task_gate:
                if self.stopped is not None:
                    return
                try:
                    await self._run_task(name, task_keys, engine, critical)
                except Exception as err:  # e.g. a task's batch built on a failed GPU context
                    failure = device_failure(err)
                    if failure is None:
                        raise
                    self._stop_device(failure)

        # Longest episodes first (the basket's 250-step budget before the base families'):
        # they start as soon as there is room, instead of running alone at the end.
        budgets = {name: self.config.budget(name) for name in by_task}
        longest_first = sorted(by_task.items(), key=lambda kv: -budgets[kv[0]])
        critical = sweep_critical_path(self.choices.executor.critical_path, budgets)
        await asyncio.gather(*(one_task(n, ks, n in critical) for n, ks in longest_first))

    async def _run_task(
        self, name: str, keys: list[EpisodeKey], engine: Engine, critical: bool
    ) -> None:
        cfg, ex, sim = self.config, self.config.executor, self.config.simulator
        task = get_task(name)
        n_slots = ex.slots(len(keys))
        gate = engine.gate

        def on_decision(spec: EpisodeSpec, seconds: float) -> None:
            gate.observe((spec.model, spec.protocol, spec.task), seconds)

        async with task_services(
            task,
            n_slots,
            engine.llm,
            engine.renderer,
            image=engine.image,
            sim_window_s=sim.window_s,
            on_decision=on_decision,
            **sim.batch_kwargs(engine.physics.kind, critical_path=critical),
        ) as svc:
            slots = asyncio.Semaphore(n_slots)

            async def one(k: EpisodeKey) -> None:
                try:
                    await run_one(k)
                except SpendCapReached as err:
                    self._cap(err)
                except RequestRejected as err:  # only fatal ones leave an episode
                    self._stop(err)
                except DeviceFailure as err:
                    self._stop_device(err)

            async def run_one(k: EpisodeKey) -> None:
                if self.stopped is not None or k.model in self.capped:
                    return
                track = cfg.track(k.track)
                # Before taking a slot: the first episodes of a family wait here for its
                # learning session without holding simulator slots.
                use = await engine.summaries.for_episode(
                    track.summaries, track.summary_source(k.model), name
                )
                spec = EpisodeSpec(
                    name,
                    int(k.seed),
                    k.model,
                    protocol=track.protocol,
                    run=int(k.run),
                    out_dir=self.run_dir / k.rel_dir,
                    demonstration_summary=use.text,
                    summary_mode=use.mode,
                    summary_from=use.source,
                    summary_status=use.status,
                    step_budget=cfg.step_budget,
                    frames=cfg.records.frames,
                )
                if use.unavailable is not None:
                    self._finish(k, unavailable_result(spec, cfg.budget(name), use.unavailable))
                    return
                async with slots, gate.slot():
                    # stopped (or capped) while this one waited for a slot
                    if self.stopped is not None or k.model in self.capped:
                        return
                    cell = self.progress.cells[(k.model, k.track, k.task)]
                    cell.running += 1
                    try:
                        result = await run_episode(spec, svc)
                    finally:
                        cell.running -= 1
                    self._finish(k, result)

            await asyncio.gather(*(one(k) for k in keys))

    def _stop(self, err: RequestRejected) -> None:
        if self.stopped is None:
            self.stopped = (
                f"model {err.endpoint!r}: {err.verdict} ({err.message}); {err.hint}. "
                "Nothing was recorded for the "
                "episodes this stopped: the same command runs them once this is fixed."
            )
            log.error("stopping the sweep: %s", self.stopped)

    def _cap(self, err: SpendCapReached) -> None:
        """A spend cap refused a call: the model's stops that model, the sweep's every one."""
        reached = err.reached
        if reached.model is None:
            if self.stopped is None:
                self.stopped = (
                    f"{reached}: no new model call was started. Nothing was recorded for the "
                    "episodes this stopped: raise the cap and run the same command to resume."
                )
                log.error("stopping the sweep: %s", self.stopped)
        elif err.endpoint not in self.capped:
            self.capped[err.endpoint] = str(reached)
            log.error("%s: no new call of model %r starts", reached, err.endpoint)

    def _stop_device(self, err: DeviceFailure) -> None:
        if self.stopped is None:
            self.device_failed = True
            self.stopped = (
                f"{err}. Nothing was recorded for the episodes this stopped: the same command "
                "runs them again in a new process."
            )
            log.error("stopping the sweep: %s", self.stopped)

    def _finish(self, k: EpisodeKey, result: EpisodeResult) -> None:
        rounds = self.config.retries.infrastructure_rounds
        again = self.ledger.infra_attempts[ledger_key(k)] < rounds
        if result.status != "infrastructure_error" or not again:  # or its last attempt failed
            self.ledger.add(k.track, k.rel_dir, result)
            return
        self.ledger.add_infrastructure_failure(k.track, k.rel_dir, result)
        set_aside(self.run_dir / k.rel_dir)
        self.progress.cells[(k.model, k.track, k.task)].retried += 1


def spend_caps(config: SweepConfig, run_dir: Path) -> SpendCaps | None:
    """The `limits.max_cost_usd` caps of `config` over what `run_dir` already spent; None when
    no cap is set (the run directory is then not read)."""
    per_model = {
        m.name: m.limits.max_cost_usd for m in config.models if m.limits.max_cost_usd is not None
    }
    total = config.limits.max_cost_usd
    if not per_model and total is None:
        return None
    return SpendCaps(per_model, total, recorded_spend(run_dir))
