"""`executor: ray`: a sweep over a Ray cluster, engine actors (`ray_engine.EngineActor`) under
the one driver. `run_ray` joins the cluster (`ray.init(address=executor.address)`: None, the
running local one or a new one; "auto", the running one; "HOST:PORT", that head node; a
caller's own `ray.init` is kept, else the checkout ships with `ray_plan.project_runtime_env`),
cuts the pending cells into about `CHUNKS_PER_ENGINE` chunks an engine (whole tasks with batched
physics) and starts the engines `ray_plan.engine_plan` plans; the limit board is a
`LimiterActor` on the driver's node. The run directory must be at the same absolute path on
every node; API keys travel to the engines in memory, never in a file. A killed driver takes its
engines with it (Ray ends the actors a driver owns); the same command resumes from the ledger.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from typing_extensions import Unpack

from vabench.config import SweepConfig
from vabench.config.choices import Choices
from vabench.llm_pool.limit_board import LimiterActor, RayBoard
from vabench.llm_pool.spend import SpendCaps
from vabench.sweep.cells import Cell, chunks, dealing_costs, dealt_choices, task_groups
from vabench.sweep.chunk_engine import (
    CLOSED,
    DONE,
    FAILED,
    LINE,
    LOST,
    STARTED,
    STATUS,
    BoardLink,
)
from vabench.sweep.driver import (
    CLOSE_TIMEOUT_S,
    TICK_S,
    Cells,
    Emit,
    Engines,
    Hooks,
    run_engines,
)
from vabench.sweep.placement import Chunk
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.ray_plan import (
    CHUNKS_PER_ENGINE,
    engine_environment,
    engine_plan,
    project_runtime_env,
    upload_failure,
)
from vabench.sweep.results import Key
from vabench.sweep.runner import SweepStopped

log = logging.getLogger(__name__)


class RayEngine:
    """The driver's handle on one engine actor (`placement.Engine`): a thread of the driver waits
    on each of its calls and reports what comes back."""

    def __init__(self, ray: Any, actor: Any, holder: str, limiter: Any, emit: Emit):
        self.ray = ray
        self.actor = actor
        self.holder = holder
        self.limiter = limiter
        self.emit = emit
        self.ended = threading.Event()
        self.threads: list[threading.Thread] = []

    def _thread(self, target: Callable[..., None], *args: Any) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True)
        self.threads.append(thread)
        thread.start()

    def start(self, tasks: Sequence[str]) -> None:
        self._thread(self._started, self.actor.start.remote(list(tasks)))

    def _started(self, ref: Any) -> None:
        try:
            info = self.ray.get(ref)
        except Exception as err:  # its config does not load there, or it died starting
            # an engine that could not even be created (no run directory there) would fail
            # the same way again: not replaced
            self._lost(err, replace=not _in_creation(err))
            return
        self.emit(STARTED, info)
        while not self.ended.wait(TICK_S):  # its status for the display
            try:
                status = self.ray.get(self.actor.engine_status.remote())
            except Exception as err:
                self._lost(err)
                return
            self.emit(STATUS, status)

    def run_chunk(self, chunk: Chunk) -> None:
        self._thread(self._stream, chunk.name, self.actor.run_chunk.remote(chunk.name, chunk.keys))

    def _stream(self, name: str, stream: Any) -> None:
        summary: dict[str, Any] = {}
        try:
            for ref in stream:
                item = self.ray.get(ref)
                if item[0] == LINE:
                    self.emit(*item)
                elif item[0] == DONE:
                    summary = item[1]
        except self.ray.exceptions.RayTaskError as err:  # the chunk's own error
            self.emit(FAILED, name, str(err))
            return
        except Exception as err:  # the engine (or its node) is gone
            self._lost(err)
            return
        self.emit(DONE, name, summary)

    def _lost(self, err: BaseException, replace: bool = True) -> None:
        if not self.ended.is_set():
            self.emit(LOST, _why(err), replace)

    def close(self) -> None:
        def closing(ref: Any) -> None:
            figures: dict[str, Any] = {}
            with contextlib.suppress(Exception):
                figures = self.ray.get(ref, timeout=CLOSE_TIMEOUT_S) or {}
            self.emit(CLOSED, figures)

        self._thread(closing, self.actor.close.remote())

    def kill(self) -> None:
        self.ended.set()
        with contextlib.suppress(Exception):
            self.ray.kill(self.actor, no_restart=True)
        if self.limiter is not None:  # the board frees what it held
            with contextlib.suppress(Exception):
                self.limiter.forget.remote(self.holder)
        for thread in self.threads:  # none of them may call Ray once the driver has left it
            if thread is not threading.current_thread():
                thread.join(timeout=5)


class RayEngines(Engines):
    """`driver.Engines` of engine actors on a Ray cluster, and their plan."""

    label = "ray"
    log = log

    def __init__(
        self,
        ray: Any,
        config: SweepConfig,
        choices: Choices,
        run_dir: Path,
        cells: dict[Cell, list[EpisodeKey]],
    ):
        from vabench.sweep.ray_engine import EngineActor

        super().__init__(config, choices, run_dir)
        self.ray = ray
        self.max_chunks = choices.executor.max_tasks
        cluster = ray.cluster_resources()
        self.engines_wanted, self.resources, self.choices = engine_plan(config, choices, cluster)
        cores, share = int(self.resources["num_cpus"]), 1
        if self.resources["num_gpus"]:
            share = round(1 / self.resources["num_gpus"])  # engines sharing a GPU
            gpus = max(1, int(cluster.get("GPU", 1)))
            cores = max(1, int(cluster.get("CPU", 1)) // (gpus * share))
        cost = dealing_costs(config, cells, "ray").__getitem__
        # engines on GPUs batch their physics: a chunk per task (every track and model of it)
        # is one batch per action instead of one per cell
        batched = self.choices.physics.batched
        units = task_groups(cells) if batched else cells
        self.choices = dealt_choices(config, cells, self.choices)  # batches' stream priorities
        parts = chunks(units, self.engines_wanted, cost, per_worker=CHUNKS_PER_ENGINE)
        # where engines share GPUs, a chunk of the critical path's task runs alone in its
        # engine (`placement.choose_engine`); with one engine a GPU that would give the
        # basket's few episodes a whole GPU
        alone = batched and share > 1
        critical = set(self.choices.executor.critical_path or ()) if alone else set()
        self.chunks = [
            Chunk(name, part, cost(part[0].task), part[0].task in critical) for name, part in parts
        ]
        # one engine a GPU at the normal MPS priority for the critical chunks, the others
        # below it
        ranked = any(c.critical for c in self.chunks)
        self.environ = engine_environment(config, cores, share, uuid.uuid4().hex[:12], ranked)
        self.remote = ray.remote(EngineActor)
        self.limiter: Any = None
        log.info(
            "ray: %d chunks (%d episodes; %s) on a cluster of %s: %d engines, each %s",
            len(self.chunks),
            sum(len(c.keys) for c in self.chunks),
            "a chunk per task: batched physics" if batched else "a chunk per cell",
            {k: v for k, v in cluster.items() if k in ("CPU", "GPU")},
            self.engines_wanted,
            self.resources,
        )

    def fits(self) -> bool:
        """Whether some node of the cluster has what one engine claims (else say so: the
        engines would wait for resources that never come)."""
        wanted = {"CPU": self.resources["num_cpus"], "GPU": self.resources["num_gpus"]}
        nodes = [n["Resources"] for n in self.ray.nodes() if n.get("Alive")]
        if any(all(node.get(k, 0) >= v for k, v in wanted.items() if v) for node in nodes):
            return True
        log.error(
            "ray: no node of the cluster has what one engine claims (%s; nodes: %s): lower "
            "render.workers (a CPU engine claims 1 + render.workers CPUs) or add such a node",
            self.resources,
            [{k: v for k, v in node.items() if k in ("CPU", "GPU")} for node in nodes],
        )
        return False

    def serve_board(
        self, stack: contextlib.ExitStack, limits: dict[str, dict[str, Any]], caps: SpendCaps | None
    ) -> BoardLink:
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        here = self.ray.get_runtime_context().get_node_id()
        self.limiter = (
            self.ray.remote(LimiterActor)
            .options(
                num_cpus=0,
                max_concurrency=10_000,
                scheduling_strategy=NodeAffinitySchedulingStrategy(here, soft=False),
            )
            .remote(limits, caps)
        )

        def end() -> None:
            with contextlib.suppress(Exception):
                self.ray.kill(self.limiter, no_restart=True)

        stack.callback(end)
        return RayBoard(self.limiter, tuple(limits), caps is not None)

    def new_engine(self, index: int, slot: int, emit: Emit, board: BoardLink | None) -> RayEngine:
        holder = f"engine-{index}-{uuid.uuid4().hex[:8]}"
        actor = self.remote.options(
            **self.resources, scheduling_strategy="SPREAD", max_restarts=0
        ).remote(self.config, self.choices, str(self.run_dir), self.environ, board, holder)
        return RayEngine(self.ray, actor, holder, self.limiter, emit)


def run_ray(
    config: SweepConfig,
    keys: Sequence[EpisodeKey],
    run_dir: Path,
    choices: Choices,
    **hooks: Unpack[Hooks],
) -> dict[Key, dict[str, Any]]:
    """Run the pending episodes of `keys` on the engines of a Ray cluster (see the module
    docstring; `driver.run_engines`)."""
    run_dir = Path(run_dir).resolve()  # engines start elsewhere: send an absolute path

    @contextlib.contextmanager
    def engines(cells: Cells) -> Iterator[Engines]:
        import ray  # the `ray` extra; only this executor needs it

        started_here = not ray.is_initialized()
        if started_here:  # (a connection made by the caller keeps its own runtime environment)
            try:
                ray.init(address=config.executor.address, runtime_env=project_runtime_env() or None)
            except Exception as err:  # Ray's own traceback says the size, not what to do
                if "working_dir" not in str(err) and "Package size" not in str(err):
                    raise
                raise SweepStopped(upload_failure(err)) from None
        try:
            yield RayEngines(ray, config, choices, run_dir, cells)
        finally:
            if started_here:
                ray.shutdown()

    return run_engines(engines, log, "ray", keys, run_dir, **hooks)


def _in_creation(err: BaseException) -> bool:
    return "error raised in its creation task" in str(err)


def _why(err: BaseException) -> str:
    """One line: the error an engine's creation raised (the last line of Ray's report), else
    the first line of Ray's."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    if not lines:
        return type(err).__name__
    return lines[-1] if _in_creation(err) else f"{type(err).__name__}: {lines[0]}"
