"""One engine that runs the chunks a driver hands it, in the process it lives in (the body of
the in-process engine, of a worker process and of a Ray engine actor). A `ChunkEngine` holds one
`runner.Engine` for its life; each chunk runs as a `LocalSweep` restricted to it, sharing the
engine's pool, renderer and in-flight limit. It never writes the ledger: `run_chunk` yields each
ledger line as its episode ends, then the chunk's summary; `serve` is its life under the
driver's commands, sending the events the driver reads.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import socket
import traceback
from collections.abc import AsyncIterator, Callable, Collection, Sequence
from contextlib import AbstractAsyncContextManager
from pathlib import Path
from typing import Any, Protocol

from vabench.config import SweepConfig
from vabench.config.choices import Choices
from vabench.llm_pool.limit_board import BoardLimits
from vabench.run_layout import PLAN, RunDir
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import ledger_key
from vabench.sweep.runner import Engine, LocalSweep, open_engine, start_compiling
from vabench.tuning import engine_env, gpu_busy
from vabench.tuning.engine_env import configure_jax

log = logging.getLogger(__name__)

LINE = "line"
"""A ledger line of `run_chunk`: (LINE, log name, record)."""
DONE = "done"
"""The last item of `run_chunk`: (DONE, summary)."""
STARTED, FAILED, STATUS, LOST, CLOSED = "started", "failed", "status", "lost", "closed"
"""The other events an engine sends its driver (`serve`, `driver`)."""
STATUS_EVERY_S = 1.0
"""How often a served engine sends its status."""


class BoardLink(Protocol):
    """How an engine reaches the sweep's limit board (`llm_pool.board_socket.BoardAddress`,
    `llm_pool.limit_board.RayBoard`)."""

    def joined(self, holder: str) -> AbstractAsyncContextManager[BoardLimits]: ...


def for_chunk(choices: Choices, part: Sequence[EpisodeKey]) -> Choices:
    """The choices a chunk runs on: with batched physics (a chunk of whole tasks) every task
    of the chunk at once, one batch each; else the engine's."""
    ex = choices.executor
    tasks = len({k.task for k in part})
    if not choices.physics.batched or tasks <= ex.max_tasks:
        return choices
    return dataclasses.replace(choices, executor=dataclasses.replace(ex, max_tasks=tasks))


class ChunkEngine:
    """One engine serving chunks (see the module docstring); every method runs in one event
    loop. `start` first, `close` last."""

    def __init__(self, config: SweepConfig, choices: Choices, run_dir: Path, dealt: bool = True):
        """`dealt`: its chunks are parts of the sweep dealt over engines (`for_chunk`); False
        for the one engine of `executor: local`, whose one chunk is the sweep, run on the
        command's `choices` as they are."""
        if not RunDir(run_dir).plan.exists():  # absent where the run directory is not shared
            raise RuntimeError(
                f"{run_dir}: no {PLAN} here on {socket.gethostname()}: the engines need a run "
                "directory that every node sees at the same path (a shared mount)"
            )
        self.config = config
        self.choices = choices
        self.run_dir = run_dir
        self.dealt = dealt
        self.engine: Engine | None = None
        self._stack: contextlib.AsyncExitStack | None = None
        self._sweeps: dict[str, LocalSweep] = {}
        self._gpus: gpu_busy.GpuBusy | None = None
        self._gpu_start: gpu_busy.Totals | None = None

    async def start(
        self,
        tasks: Collection[str] = (),
        board: BoardLink | None = None,
        holder: str = "",
        sample_gpu: bool = False,
    ) -> dict[str, Any]:
        """Open the engine, its limits those of `board` (as `holder`), and with Warp physics
        on a GPU start compiling the kernels of `tasks` in the background (a chunk's family
        waits for its own kernels only; a failure is logged and each chunk compiles its own).
        `sample_gpu`: keep this engine's GPU's busy share for the driver's report. Returns
        where and how it runs."""
        configure_jax(self.choices.physics)
        import jax

        stack = contextlib.AsyncExitStack()
        try:
            if sample_gpu:
                self._gpus = stack.enter_context(gpu_busy.sampling())
            self._gpu_start = self._gpus.totals() if self._gpus is not None else None
            limits = None
            if board is not None:  # closed after the pool: it gives back what it held
                limits = await stack.enter_async_context(board.joined(holder))
            opened = open_engine(
                self.config,
                self.choices,
                self.run_dir,
                shared_limits=limits,
                spend_caps=limits.spend if limits is not None else None,
            )
            self.engine = await stack.enter_async_context(opened)
        except BaseException:
            await stack.aclose()
            raise
        self._stack = stack
        try:
            first = self.choices.executor.critical_path or ()
            await start_compiling(self.engine, self.choices, tasks, first)
        except Exception as err:  # each chunk compiles its own families anyway
            log.warning("compiling the sweep's Warp kernels ahead failed (%r); chunks will", err)
        return {
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "physics": self.engine.physics.label,
            "jax": jax.default_backend(),
            "limit": self.engine.gate.limit,
            "environment": {k: os.environ.get(k) for k in engine_env.REPORTED},
        }

    async def run_chunk(
        self, name: str, keys: Sequence[EpisodeKey]
    ) -> AsyncIterator[tuple[Any, ...]]:
        """Run the episodes `keys` in this engine; yields (LINE, log, record) as each ledger
        line is written, then (DONE, summary). An error of the chunk itself is raised after its
        lines."""
        assert self.engine is not None, "start() first"
        lines: asyncio.Queue[tuple[str, dict[str, Any]]] = asyncio.Queue()
        sweep = LocalSweep(
            self.config,
            keys,
            self.run_dir,
            for_chunk(self.choices, keys) if self.dealt else self.choices,
            ledger_sink=lambda log, record: lines.put_nowait((log, record)),
        )
        self._sweeps[name] = sweep
        running = asyncio.create_task(sweep.run(self.engine))
        line: asyncio.Future[tuple[str, dict[str, Any]]] | None = None
        try:
            while not running.done():
                line = asyncio.ensure_future(lines.get())
                await asyncio.wait({line, running}, return_when=asyncio.FIRST_COMPLETED)
                if line.done():
                    yield (LINE, *line.result())
                else:
                    line.cancel()
            while not lines.empty():
                yield (LINE, *lines.get_nowait())
            progress = running.result()  # raises the chunk's error
            yield (DONE, self._summary(sweep, keys, progress.total().retried))
        finally:
            self._sweeps.pop(name, None)
            if line is not None:
                line.cancel()
            if not running.done():  # its episodes unwound before the engine may close
                running.cancel()
                await asyncio.wait({running})

    def _summary(
        self, sweep: LocalSweep, keys: Sequence[EpisodeKey], retried: int
    ) -> dict[str, Any]:
        records = [sweep.ledger.records.get(ledger_key(k)) for k in keys]
        return {
            "episodes": len(keys),
            "recorded": sum(r is not None for r in records),
            "unscored": sum(
                r is not None and r["status"] not in ("success", "failure") for r in records
            ),
            "retried": retried,
            "stopped": sweep.stopped,
            "device_failed": sweep.device_failed,
            "physics": self.choices.physics.label,
            "in_flight": sweep.gate.reason if sweep.gate is not None else None,
        }

    def status(self) -> dict[str, Any]:
        """The engine's state for the driver's display: episodes running per model/track,
        the in-flight gate, and the model calls, tokens and cost of its pool so far."""
        running: dict[str, int] = {}
        for sweep in list(self._sweeps.values()):
            for (model, track, _task), counts in sweep.progress.cells.items():
                if counts.running:
                    key = f"{model}/{track}"
                    running[key] = running.get(key, 0) + counts.running
        out: dict[str, Any] = {"running": running, "chunks": len(self._sweeps), **self._gpu()}
        if self.engine is not None:
            stats = list(self.engine.llm.stats().values())
            gate = self.engine.gate
            out |= {
                "in_flight": gate.in_flight,
                "limit": gate.limit,
                "reason": gate.reason,
                "calls": sum(s.succeeded for s in stats),
                "tokens": sum(s.usage.total_tokens for s in stats),
                "cost": sum(s.cost_usd for s in stats),
                "calls_in_flight": sum(s.in_flight for s in stats),
            }
        return out

    def _gpu(self) -> dict[str, Any]:
        """Its GPU's mean busy share since the engine started and the most memory used."""
        if self._gpus is None:
            return {}
        totals = self._gpus.totals()
        return {
            "gpu_busy": totals.mean_since(self._gpu_start),
            "gpu_memory_mib": totals.memory_max_mib,
        }

    async def close(self) -> dict[str, Any]:
        """Close the engine; returns its GPU's figures over its life (empty without them)."""
        figures = self._gpu()
        if self._stack is not None:  # (stopping the GPU sampler waits for its last reading)
            stack, self._stack = self._stack, None
            await stack.aclose()
        return figures


Command = tuple[Any, ...]
"""What a driver tells a served engine: ("run", name, keys) or ("close",)."""


async def serve(
    make: Callable[[], ChunkEngine],
    board: BoardLink | None,
    commands: asyncio.Queue[Command | None],
    send: Callable[[tuple[Any, ...]], None],
    on_chunk: Callable[[Sequence[EpisodeKey]], None] = lambda keys: None,
) -> None:
    """An engine's life under a driver: made (else LOST, not to be replaced: another would fail
    the same way), started with the limits of `board` (STARTED, or LOST), its STATUS every
    `STATUS_EVERY_S`, each ("run", name, keys) of `commands` run at once (its LINEs, then DONE
    or FAILED), until ("close",) or None (the driver is gone); then its chunks still running
    are cancelled (nothing of them would be recorded) and it is closed (CLOSED). Cancelled
    itself (an in-process engine ended at once), it cancels its chunks and closes too."""
    try:
        engine = make()
    except Exception:
        send((LOST, f"it could not be made:\n{traceback.format_exc()}", False))
        return
    try:
        send((STARTED, await engine.start((), board)))
    except Exception:
        send((LOST, f"it did not start:\n{traceback.format_exc()}", True))
        return

    async def report() -> None:
        while True:
            send((STATUS, engine.status()))
            await asyncio.sleep(STATUS_EVERY_S)

    async def run(name: str, keys: list[EpisodeKey]) -> None:
        try:
            async for item in engine.run_chunk(name, keys):
                send(item if item[0] == LINE else (DONE, name, item[1]))
        except Exception:
            send((FAILED, name, traceback.format_exc()))

    ticker = asyncio.create_task(report())
    running: set[asyncio.Task[None]] = set()
    try:
        while (command := await commands.get()) is not None and command[0] == "run":
            _, name, keys = command
            on_chunk(keys)
            task = asyncio.create_task(run(name, keys))
            running.add(task)
            task.add_done_callback(running.discard)
    finally:
        ticker.cancel()
        for task in running:
            task.cancel()
        await asyncio.gather(*running, return_exceptions=True)
        figures = await engine.close()
    send((CLOSED, figures))
