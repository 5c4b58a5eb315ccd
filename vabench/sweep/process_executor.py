"""`executor: processes`: the sweep's engines as spawned worker processes of one host, for hosts
where one process is CPU-bound (C MuJoCo, a CPU-heavy embedded policy) and, with batched
physics, for engine processes sharing a GPU under CUDA MPS. Each holds one
`chunk_engine.ChunkEngine` for its life and runs the chunks of `plan_chunks` on the sweep's
`Choices` (the records equal the local executor's); spawned, never forked (the parent holds JAX
and thread pools), it talks to the driver over two pipes, exits with its parent, leaves Ctrl-C
to the driver, and starts with its share of the cores, its GPU and its MPS priority.
"""

from __future__ import annotations

import asyncio
import contextlib
import cProfile
import logging
import multiprocessing
import os
import re
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from typing_extensions import Unpack

from vabench import switches
from vabench.children import (
    CORES_VARIABLE,
    child_logging,
    children_ignore_sigint,
    exit_with_parent,
    ignore_sigint,
    process_age_s,
    started_with,
)
from vabench.config import SweepConfig
from vabench.config.choices import Choices
from vabench.llm_pool.board_socket import BoardAddress, BoardServer
from vabench.llm_pool.limit_board import LimitBoard
from vabench.llm_pool.spend import SpendCaps
from vabench.run_layout import RunDir
from vabench.sweep.cells import (
    Cell,
    bins,
    chunks,
    dealing_costs,
    dealt_choices,
    episode_costs,
    task_groups,
)
from vabench.sweep.chunk_engine import (
    LOST,
    BoardLink,
    ChunkEngine,
    Command,
    serve,
)
from vabench.sweep.driver import Cells, Emit, Engines, Hooks, run_engines
from vabench.sweep.placement import Chunk
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import Key
from vabench.sweep.runner import compile_ahead
from vabench.tuning import engine_env, kernel_profile, mps, precompile
from vabench.tuning.engine_env import child_environment, gpu_for_worker

log = logging.getLogger(__name__)


def plan_chunks(
    config: SweepConfig,
    cells: dict[Cell, list[EpisodeKey]],
    choices: Choices,
    costs: Mapping[str, float] | None = None,
) -> list[tuple[str, list[EpisodeKey]]]:
    """The chunks the engines take. With batched physics (Warp, MJX: an action costs the same
    for 10 slots as for 200) whole tasks, every track and model, dealt over the engines, each
    stepping one batch per task at once (`cells.bins`); else cells cut to keep every core busy
    to the end (`cells.chunks`). Where engines share GPUs under MPS, a task on the sweep's
    critical path (`critical_tasks`) is a chunk of its own, first, for an engine of its own:
    its episodes take several times the others' decisions, and each decision would wait for
    the process's other batches (docs/PERFORMANCE.md). An episode weighs `costs` (by task;
    `cells.episode_costs`), step budgets where none are given."""
    workers = choices.executor.max_tasks
    costs = costs or episode_costs(config, (t for _, _, t in cells), {})
    cost = costs.__getitem__
    if not choices.physics.batched:
        return chunks(cells, min(workers, len(cells)), cost)
    groups = task_groups(cells)
    critical = critical_tasks(config, cells, choices)
    alone = [(task, keys) for (task,), keys in groups.items() if task in critical]
    rest = {group: keys for group, keys in groups.items() if group[0] not in critical}
    return alone + (bins(rest, workers, cost) if rest else [])


def critical_tasks(
    config: SweepConfig, cells: dict[Cell, list[EpisodeKey]], choices: Choices
) -> set[str]:
    """The critical path's tasks that get an engine process of their own (`plan_chunks`), at
    the normal MPS priority (`critical_environment`): where engine processes share GPUs under
    MPS (batched physics, several engines). Without MPS (one engine process per GPU): none."""
    ex = choices.executor
    if not (ex.mps and ex.max_tasks > 1):
        return set()
    return set(dealt_choices(config, cells, choices).executor.critical_path or ())


def worker_shares(choices: Choices, workers: int) -> dict[str, str]:
    """Each of `workers` engine processes' share of its GPU and of the host's cores
    (`engine_env.worker_shares`). The critical path's process of its own is not counted: its
    few episodes need a fraction of the others' share, and counting it would leave the others'
    embedded servers below the cores from which they have processes of their own."""
    sharing = min(workers, choices.executor.max_tasks)
    return engine_env.worker_shares(choices.machine.cores, len(choices.machine.gpus), sharing)


def critical_environment(
    choices: Choices, shared: Mapping[str, str], part: Sequence[EpisodeKey], critical: set[str]
) -> dict[str, str]:
    """What the engine of `part` starts with beyond the environment `shared` by all engines:
    for the critical path's process (a chunk of `critical` tasks), a normal MPS client while
    every other engine is below normal (`engine_env.critical_path_environment`); nothing for
    the other engines."""
    if not critical or not {k.task for k in part} <= critical:
        return {}
    shared_cores = int(shared.get(CORES_VARIABLE, "1"))
    return engine_env.critical_path_environment(shared_cores, choices.machine.cores)


# -- the engine process ----------------------------------------------------------------------
@dataclass(frozen=True)
class WorkerSpec:
    """What an engine process is started with (pickled into it)."""

    config: SweepConfig
    choices: Choices
    run_dir: Path
    board: BoardAddress | None
    parent: int


def _worker(spec: WorkerSpec, commands: Connection, lines: Connection) -> None:
    """An engine process's main: serve chunks until told to close or the parent is gone."""
    ignore_sigint()  # the driver ends this process
    exit_with_parent(spec.parent)  # its own children (render workers) see their pipes close
    child_logging(RunDir(spec.run_dir).worker_log(os.getpid()))
    kernel_profile.record_in_background()  # where VABENCH_KERNEL_PROFILE asks for it
    # `profiling.cprofile_dir`: a cProfile of this process's event loop thread over its life
    # (`<pid>-<first episode>.prof`): the engine, the model client, an embedded server in its
    # process, the agent's decisions; for hosts with no sampling profiler
    folder = switches.get("profile_dir")
    profile = cProfile.Profile() if folder else None
    first: list[EpisodeKey] = []
    if profile is not None:
        profile.enable()
    try:
        asyncio.run(_serve(spec, commands, lines, first))
    finally:
        if profile is not None and folder:
            profile.disable()
            Path(folder).mkdir(parents=True, exist_ok=True)
            name = re.sub(r"[^\w.-]+", "_", first[0].as_id().replace("/", "-")) if first else "idle"
            profile.dump_stats(Path(folder) / f"{os.getpid()}-{name}.prof")


async def _serve(
    spec: WorkerSpec, commands: Connection, lines: Connection, first: list[EpisodeKey]
) -> None:
    loop = asyncio.get_running_loop()
    inbox: asyncio.Queue[Command | None] = asyncio.Queue()

    def receive() -> None:  # None once the driver's end of the pipe is gone
        with contextlib.suppress(EOFError, OSError):
            while True:
                loop.call_soon_threadsafe(inbox.put_nowait, commands.recv())
        loop.call_soon_threadsafe(inbox.put_nowait, None)

    threading.Thread(target=receive, name="commands", daemon=True).start()

    def send(item: tuple[Any, ...]) -> None:  # from this loop's thread only
        with contextlib.suppress(OSError):  # the driver is gone: this process ends with it
            lines.send(item)

    def on_chunk(keys: Sequence[EpisodeKey]) -> None:
        if not first:
            first.append(keys[0])
            age = process_age_s()
            if age is not None:  # the spawn's start: its interpreter, imports and engine
                log.info("engine process: its first chunk %.1f s after the process started", age)

    def make() -> ChunkEngine:
        return ChunkEngine(spec.config, spec.choices, spec.run_dir)

    await serve(make, spec.board, inbox, send, on_chunk)


class ProcessEngine:
    """The driver's handle on one engine process (`placement.Engine`)."""

    def __init__(self, index: int, emit: Emit, spec: WorkerSpec, env: Mapping[str, str]):
        self.index = index
        self.emit = emit
        self.spec = spec
        self.env = dict(env)
        self.process: multiprocessing.process.BaseProcess | None = None
        self.reader: threading.Thread | None = None
        self.closing = False

    def start(self, tasks: Sequence[str]) -> None:
        """Spawn the process (the kernels of `tasks` are compiled by the parent,
        `ProcessEngines.prepare`)."""
        context = multiprocessing.get_context("spawn")
        commands, self.commands = context.Pipe(duplex=False)
        self.lines, lines = context.Pipe(duplex=False)
        with started_with(self.env), children_ignore_sigint():
            self.process = context.Process(
                target=_worker, args=(self.spec, commands, lines), name=f"engine-{self.index}"
            )
            self.process.start()
        commands.close()  # the child's ends: its death then reads as the end of the pipe
        lines.close()
        self.reader = threading.Thread(target=self._read, name=f"engine-{self.index}", daemon=True)
        self.reader.start()

    def _read(self) -> None:
        with contextlib.suppress(EOFError, OSError):
            while True:
                self.emit(*self.lines.recv())
        assert self.process is not None
        self.process.join(timeout=5)
        self.emit(LOST, _death(self.process.exitcode), True)

    def _send(self, message: tuple[Any, ...]) -> None:
        with contextlib.suppress(OSError):  # a dead process's end: its LOST is on its way
            self.commands.send(message)

    def run_chunk(self, chunk: Chunk) -> None:
        self._send(("run", chunk.name, chunk.keys))

    def close(self) -> None:
        self.closing = True
        self._send(("close",))

    def kill(self) -> None:
        process = self.process
        if process is not None and self.closing:  # it is closing: its last writes (a profile)
            process.join(timeout=30)
        if process is not None and process.is_alive():
            process.terminate()
            process.join(timeout=10)
            if process.is_alive():
                process.kill()
                process.join(timeout=10)
        if self.reader is not None and self.reader is not threading.current_thread():
            self.reader.join(timeout=10)  # every whole line it sent is in the driver's queue


def _death(code: int | None) -> str:
    how = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
    return (
        f"a worker process died ({how}: killed, out of memory, or a crash in native code: its "
        "last lines are above)"
    )


class ProcessEngines(Engines):
    """`driver.Engines` of worker processes on this host, and their plan."""

    label = "processes"
    unit = "worker processes"
    log = log

    def __init__(
        self,
        config: SweepConfig,
        choices: Choices,
        run_dir: Path,
        cells: dict[Cell, list[EpisodeKey]],
    ):
        super().__init__(config, choices, run_dir)
        self.cells = cells
        costs = dealing_costs(config, cells, self.label)
        self.critical = critical_tasks(config, cells, choices)
        self.chunks = [
            Chunk(name, part, costs[part[0].task], part[0].task in self.critical)
            for name, part in plan_chunks(config, cells, choices, costs)
        ]
        # batched physics: every chunk at once (`plan_chunks` makes at most `max_tasks`, plus
        # the critical path's own)
        batched = choices.physics.batched
        self.engines_wanted = (
            len(self.chunks) if batched else min(choices.executor.max_tasks, len(self.chunks))
        )
        self.sent = dealt_choices(config, cells, choices)
        """What the engines run on: with batched physics, the whole sweep's critical path."""
        self.env = child_environment(choices.physics) | worker_shares(choices, self.engines_wanted)
        if self.critical:  # every engine process below the critical path's on the GPU
            self.env[mps.PRIORITY_VARIABLE] = mps.BELOW_NORMAL
        self.gpus = choices.machine.gpus

    def serve_board(
        self, stack: contextlib.ExitStack, limits: dict[str, dict[str, Any]], caps: SpendCaps | None
    ) -> BoardLink:
        server = BoardServer(LimitBoard(limits, caps))
        address = server.start()
        stack.callback(server.close)
        return BoardAddress(address, tuple(limits), caps is not None)

    def prepare(self, stack: contextlib.ExitStack) -> None:
        """Before the MPS daemon: this process is no client (its CUDA context is made first).
        The kernels compile in the background (each engine's families wait for their own); the
        engine processes share the GPU through the sweep's own MPS daemon, closed with `stack`
        once its clients are gone."""
        compiling = self._precompile()
        if compiling is not None:  # long over unless the sweep was: its children end theirs

            def join(failed: type[BaseException] | None, *_: Any) -> None:
                compiling.join(timeout=0 if failed else precompile.CHILD_TIMEOUT_S)

            stack.push(join)
        executor = self.choices.executor
        clients = engine_env.shared_gpu_clients(stack, executor.max_tasks) if executor.mps else {}
        self.env.update(clients)
        if clients:  # the sweep's own daemon numbers the GPUs it sees 0..n-1
            devices, self.gpus = mps.client_devices(self.choices.machine.gpus)
            self.env.update(devices)
        seen = {
            k: v
            for k in engine_env.REPORTED
            if (v := self.env.get(k, os.environ.get(k))) is not None
        }
        log.info(
            "processes: %d cells (%d episodes) in %d chunks, %d at once; engines run with %s%s",
            len(self.cells),
            sum(len(v) for v in self.cells.values()),
            len(self.chunks),
            self.engines_wanted,
            " ".join(f"{k}={v}" for k, v in seen.items()) or "this environment",
            f", one of GPUs {','.join(self.gpus)} each" if len(self.gpus) > 1 else "",
        )

    def _precompile(self) -> precompile.Compiling | None:
        """Every family's Warp kernels compiled once, here, in the background (`compile_ahead`),
        before the engines start: each engine's families wait for their own kernels (engines
        compiling them would compile, one after another under the machine's lock, the modules
        the families share). With `VABENCH_WARP_PRECOMPILE=first`, returns once it has ended."""
        size = (self.config.render.width, self.config.render.height)
        first = self.sent.executor.critical_path or ()
        tasks = {task for _, _, task in self.cells}
        compiling = compile_ahead(tasks, self.choices, size, first)
        if compiling is not None and switches.get("warp_precompile") == "first":
            compiling.join()
        return compiling

    def new_engine(
        self, index: int, slot: int, emit: Emit, board: BoardLink | None
    ) -> ProcessEngine:
        env = dict(self.env)
        gpu = gpu_for_worker(slot, self.gpus)
        if gpu is not None:  # before anything there initialises CUDA
            env["CUDA_VISIBLE_DEVICES"] = gpu
        if slot < len(self.chunks):  # a slot a chunk each: the critical path's ahead
            part = self.chunks[slot].keys
            env |= critical_environment(self.choices, self.env, part, self.critical)
        assert board is None or isinstance(board, BoardAddress)
        spec = WorkerSpec(self.config, self.sent, self.run_dir, board, os.getpid())
        return ProcessEngine(index, emit, spec, env)


def run_processes(
    config: SweepConfig,
    keys: Sequence[EpisodeKey],
    run_dir: Path,
    choices: Choices,
    **hooks: Unpack[Hooks],
) -> dict[Key, dict[str, Any]]:
    """Run the pending episodes of `keys` in engine processes on `choices`
    (`driver.run_engines`)."""
    run_dir = Path(run_dir).resolve()

    def engines(cells: Cells) -> contextlib.nullcontext[Engines]:
        return contextlib.nullcontext(ProcessEngines(config, choices, run_dir, cells))

    return run_engines(engines, log, "processes", keys, run_dir, **hooks)
