"""The driver of a Ray sweep (`ray_executor.run_ray` starts it; see `ray_executor`'s docstring,
3-8): `ClusterSweep` starts the limit board and the engines, hands out chunks as engines have
room, appends the ledger lines they stream back (the only writer of the ledger), puts the
unfinished episodes of a dead engine back in the queue and starts another in its place, polls
the engines' statuses for the display, and closes everything at the end. It keeps each
engine's time (`ray_plan.EngineClock`: start-up, working, waiting for work) and its GPU's busy
share, and logs them when the sweep ends (`engine_report`).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from vabench.config import SweepConfig
from vabench.run_layout import DUPLICATES
from vabench.sweep.cells import PROGRESS_EVERY_S, chunks, task_groups
from vabench.sweep.choices import Choices
from vabench.sweep.display import Status, Tally, with_reports
from vabench.sweep.limiter import shared_endpoints
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.ray_engine import DONE, LINE
from vabench.sweep.ray_plan import (
    CHUNKS_PER_ENGINE,
    Chunk,
    EngineHandle,
    engine_environment,
    engine_plan,
    next_placement,
    with_critical_path,
)
from vabench.sweep.results import Ledger, LedgerError, ledger_key
from vabench.sweep.runner import spend_caps
from vabench.tasks import REGISTRY

# the driver's lines are `ray_executor`'s, as before the driver had a module of its own (log
# filters and the tests select them by that logger's name)
log = logging.getLogger("vabench.sweep.ray_executor")

TICK_S = 1.0
"""Seconds between display updates (and the longest the driver waits for an engine)."""
MAX_ENGINE_RESTARTS = 16
"""Engines started in place of dead ones, in one invocation."""
ENGINE_START_TIMEOUT_S = 900.0
"""How long the driver waits for an engine while none runs (a node may download the project,
compile, build demonstrations) before it gives up, listing what did not run."""


class ClusterSweep:
    """The driver's loop (see `ray_executor`'s docstring, 3-8)."""

    def __init__(
        self,
        ray: Any,
        config: SweepConfig,
        choices: Choices,
        keys: Sequence[EpisodeKey],
        run_dir: Path,
        cells: dict[tuple[str, str, str], list[EpisodeKey]],
        on_status: Callable[[Status], None] | None,
    ):
        from vabench.sweep.ray_engine import EngineActor

        self.ray = ray
        self.config = config
        self.run_dir = run_dir
        self.on_status = on_status
        self.ledger = Ledger.open(run_dir)  # the only writer
        self.tally = Tally(run_dir, keys)
        cluster = ray.cluster_resources()
        self.engines_wanted, self.resources, self.choices = engine_plan(config, choices, cluster)
        cores, share = int(self.resources["num_cpus"]), 1
        if self.resources["num_gpus"]:
            share = round(1 / self.resources["num_gpus"])  # engines sharing a GPU
            gpus = max(1, int(cluster.get("GPU", 1)))
            cores = max(1, int(cluster.get("CPU", 1)) // (gpus * share))
        # a task the registry lacks fails in its chunk
        cost = lambda task: config.budget(task) if task in REGISTRY else 1  # noqa: E731
        # Engines on GPUs batch their physics: a chunk per task (every track and model of it)
        # is one batch per action instead of one per cell (measured on 2 x H100: 16 batches of
        # <= 10 slots per engine, stepped one after the other, made 1.1 episodes/s).
        self.batched = self.choices.physics.batched
        units = task_groups(cells) if self.batched else cells
        if self.batched:  # where batches have stream priorities
            budgets = {key[0]: cost(key[0]) for key in units}
            self.choices = with_critical_path(self.choices, budgets)
        parts = chunks(units, self.engines_wanted, cost, per_worker=CHUNKS_PER_ENGINE)
        # where engines share GPUs (`executor.actors` above them), a chunk of the critical
        # path's task runs alone in its engine (`ray_plan.choose_engine`); with one engine a
        # GPU that would give the basket's few episodes a whole GPU
        alone = self.batched and share > 1
        critical = set(self.choices.executor.critical_path or ()) if alone else set()
        self.queue: collections.deque[Chunk] = collections.deque(
            Chunk(
                name,
                [ledger_key(k) for k in part],
                cost(part[0].task),
                critical=part[0].task in critical,
            )
            for name, part in parts
        )
        # one engine a GPU at the normal MPS priority for the critical chunks, the others
        # below it (the processes executor's rule for its critical process)
        ranked = any(c.critical for c in self.queue)
        self.environ = engine_environment(config, cores, share, uuid.uuid4().hex[:12], ranked)
        self.total = len(self.queue)
        self.done = 0
        self.failures: list[Chunk] = []
        self.stopped: list[str] = []
        self.engines: list[EngineHandle] = []
        self.restarts = 0
        self.remote = ray.remote(EngineActor)
        self.document = config.document()
        self.shared = sorted(shared_endpoints(config.models, config.embedded_models))
        self.caps = spend_caps(config, self.run_dir)
        """The spend caps, kept by the limit board for every engine; None: no cap."""
        self.limiter: Any = None
        self.max_chunks = choices.executor.max_tasks
        self._changed = False
        """A chunk ended or an engine came or went since the last progress line."""
        self.started_at = time.monotonic()
        log.info(
            "ray: %d chunks (%d episodes; %s) on a cluster of %s: %d engines, each %s%s",
            self.total,
            sum(len(c.keys) for c in self.queue),
            "a chunk per task: batched physics" if self.batched else "a chunk per cell",
            {k: v for k, v in cluster.items() if k in ("CPU", "GPU")},
            self.engines_wanted,
            self.resources,
            f"; limits of {', '.join(self.shared)} kept by one board" if self.shared else "",
        )
        if self.caps is not None:
            log.info("ray: the spend caps are kept by the limit board for every engine")

    # -- the loop ------------------------------------------------------------------------------
    def run(self) -> None:
        if not self._fits_a_node():
            self.failures.extend(self.queue)
            self.queue.clear()
            return
        finished = False
        try:
            self._start_limiter()
            for _ in range(self.engines_wanted):
                self._start_engine()
            self._loop()
            finished = True
        finally:
            self._end(gracefully=finished)

    def _loop(self) -> None:
        last_log = time.monotonic()
        idle_since = time.monotonic()
        while self.queue or any(e.chunks for e in self.engines):
            self._hand_out()
            waiting: dict[Any, tuple[EngineHandle, Chunk | None]] = {}
            for e in self.engines:
                if e.dead:
                    continue
                if e.starting is not None:
                    waiting[e.starting] = (e, None)
                for stream, running in e.chunks.items():
                    waiting[stream] = (e, running)
            ready: list[Any] = []
            if waiting:
                ready = self._wait(list(waiting))
            else:
                time.sleep(TICK_S)
            for ref in ready:
                engine, chunk = waiting[ref]
                if engine.dead:  # died while handling an earlier one of this batch
                    continue
                if chunk is None:
                    self._started(engine)
                else:
                    self._next_item(engine, ref, chunk)
            self._poll_statuses()
            if any(e.ready for e in self.engines):
                idle_since = time.monotonic()
            elif not self._can_start() or time.monotonic() - idle_since > ENGINE_START_TIMEOUT_S:
                self._give_up()
            self.tally.refresh()
            if self.on_status is not None:
                self.on_status(self.status())
            if self._changed or time.monotonic() - last_log >= PROGRESS_EVERY_S:
                last_log, self._changed = time.monotonic(), False
                self._log_progress()

    def _wait(self, refs: list[Any]) -> list[Any]:
        """The references of `refs` ready within `TICK_S` (all that are, once one is)."""
        try:
            ready, _ = self.ray.wait(refs, num_returns=1, timeout=TICK_S)
            if ready:
                ready, _ = self.ray.wait(refs, num_returns=len(refs), timeout=0)
        except SystemError as err:  # Ctrl-C's `Interrupted`, raised inside Ray's own code
            if isinstance(err.__cause__, Exception):
                raise err.__cause__ from None
            raise
        return ready

    def _log_progress(self) -> None:
        log.info(
            "ray: chunks %d/%d done (%d failed), %d running on %d engines | episodes recorded "
            "%d/%d",
            self.done,
            self.total,
            len(self.failures),
            sum(len(e.chunks) for e in self.engines),
            sum(e.ready for e in self.engines),
            self.tally.status().total().done,
            len(self.tally.planned),
        )

    # -- engines -------------------------------------------------------------------------------
    def _start_limiter(self) -> None:
        if not self.shared and self.caps is None:
            return
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        from vabench.sweep.limiter import LimiterActor

        here = self.ray.get_runtime_context().get_node_id()
        limits = shared_endpoints(self.config.models, self.config.embedded_models)
        self.limiter = (
            self.ray.remote(LimiterActor)
            .options(
                num_cpus=0,
                max_concurrency=10_000,
                scheduling_strategy=NodeAffinitySchedulingStrategy(here, soft=False),
            )
            .remote(limits, self.caps)
        )

    def _fits_a_node(self) -> bool:
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

    def _start_engine(self) -> None:
        index = len(self.engines)
        holder = f"engine-{index}-{uuid.uuid4().hex[:8]}"
        actor = self.remote.options(
            **self.resources,
            scheduling_strategy="SPREAD",
            max_restarts=0,
        ).remote(
            self.document,
            self.choices,
            str(self.run_dir),
            self.environ,
            self.limiter,
            self.shared,
            holder,
            self.caps is not None,
        )
        # the families left to run (a key is (model, track, task, seed, run)): compiled at start
        tasks = sorted({key[2] for c in self.queue for key in c.keys})
        self.engines.append(EngineHandle(index, actor, holder, actor.start.remote(tasks)))

    def _can_start(self) -> bool:
        return any(e.starting is not None and not e.dead for e in self.engines)

    def _started(self, engine: EngineHandle) -> None:
        try:
            engine.info = self.ray.get(engine.starting)
        except Exception as err:  # its config does not load there, or it died starting
            self._lost(engine, err)
            return
        engine.starting = None
        engine.clock.started_at = time.monotonic()
        engine.status = {"limit": engine.info.get("limit", 1)}
        self._changed = True
        log.info("ray: engine %d started: %s", engine.index, engine.info)

    def _lost(self, engine: EngineHandle, err: BaseException) -> None:
        """`engine` died: its chunks' episodes without a record go back to the queue's front,
        the limit board frees what it held, and another engine takes its place."""
        engine.dead = True
        engine.clock.end(time.monotonic())
        self._changed = True
        requeued = 0
        for chunk in reversed(list(engine.chunks.values())):
            left = [k for k in chunk.keys if k not in self.ledger.records]
            if left:
                name = chunk.name if chunk.name.endswith(" (again)") else f"{chunk.name} (again)"
                self.queue.appendleft(Chunk(name, left, chunk.cost, chunk.critical))
                self.total += 1
                requeued += len(left)
            self.done += 1  # this try of the chunk has ended
        engine.chunks.clear()
        with contextlib.suppress(Exception):
            self.ray.kill(engine.actor, no_restart=True)
        if self.limiter is not None:
            self.limiter.forget.remote(engine.holder)
        # an engine that could not even be created (its config does not load on that node, no
        # run directory there) would fail the same way again: not replaced
        restart = self.restarts < MAX_ENGINE_RESTARTS and not _in_creation(err)
        log.warning(
            "ray: engine %d (%s) is gone: %s; %d unfinished episodes go back to the queue%s",
            engine.index,
            engine.info.get("host", "not started"),
            _why(err),
            requeued,
            "; starting another engine" if restart else "; no engine is started in its place",
        )
        if restart:
            self.restarts += 1
            self._start_engine()

    def _give_up(self) -> None:
        """No engine runs and none will: what is left is not run this time."""
        log.error(
            "ray: no engine is running and %s (each claims %s); %d chunks not run",
            f"none has started in {ENGINE_START_TIMEOUT_S:.0f} s"
            if self._can_start()
            else "none is starting",
            self.resources,
            len(self.queue),
        )
        self.failures.extend(self.queue)
        self.queue.clear()
        for e in self.engines:
            if not e.dead and e.starting is not None:
                e.dead = True
                e.clock.end(time.monotonic())
                with contextlib.suppress(Exception):
                    self.ray.kill(e.actor, no_restart=True)

    # -- chunks --------------------------------------------------------------------------------
    def _hand_out(self) -> None:
        """Give the queue's chunks to engines with room, the least loaded first, a critical
        chunk alone (`ray_plan.next_placement`, `choose_engine`)."""
        records = self.ledger.records
        while self.queue and not self.stopped:
            placed = next_placement(self.engines, self.queue, records, self.max_chunks)
            if placed is None:
                return
            at, best = placed
            chunk = self.queue[at]
            del self.queue[at]
            best.given.append(chunk)
            best.clock.work_began(time.monotonic())
            best.chunks[best.actor.run_chunk.remote(chunk.name, chunk.keys)] = chunk
            log.info("ray: chunk %s (%d episodes) to %s", chunk.name, len(chunk.keys), _host(best))
            if chunk.critical and not best.lead:  # its GPU's normal engine busy or not started
                log.warning(
                    "ray: critical chunk %s runs below normal MPS priority on %s: the engines "
                    "at normal priority on its GPU go ahead of it",
                    chunk.name,
                    _host(best),
                )

    def _next_item(self, engine: EngineHandle, stream: Any, chunk: Chunk) -> None:
        ray = self.ray
        try:
            ref = next(stream)
            item = ray.get(ref)
        except StopIteration:  # ended without its summary (never, but not a reason to hang)
            self._chunk_over(engine, stream)
            return
        except ray.exceptions.RayTaskError as err:  # the chunk's own error
            self._chunk_over(engine, stream)
            self.failures.append(chunk)
            log.error("ray: chunk %s failed on %s:\n%s", chunk.name, _host(engine), err)
            return
        except ray.exceptions.RayError as err:  # the engine (or its node) is gone
            self._lost(engine, err)
            return
        if item[0] == LINE:
            if self._append(item[1], item[2]):
                engine.clock.episodes += 1
        elif item[0] == DONE:
            self._chunk_over(engine, stream)
            summary = item[1]
            log.info("ray: chunk %s done on %s: %s", chunk.name, _host(engine), summary)
            if summary.get("stopped") and not self.stopped:
                self.stopped.append(summary["stopped"])
                self.queue.clear()

    def _chunk_over(self, engine: EngineHandle, stream: Any) -> None:
        engine.chunks.pop(stream, None)
        if not engine.chunks:
            engine.clock.work_ended(time.monotonic())
        self.done += 1
        self._changed = True

    def _append(self, name: str, record: dict[str, Any]) -> bool:
        """Append a ledger line; False when it was an episode's second record."""
        try:
            self.ledger.append_line(name, record)
        except LedgerError as err:  # an episode reported twice (an engine taken for dead)
            log.warning("ray: %s; kept in %s", err, DUPLICATES)
            self.ledger.add_duplicate(record)
            return False
        return True

    # -- status --------------------------------------------------------------------------------
    def _poll_statuses(self) -> None:
        ray = self.ray
        for e in self.engines:
            if not e.ready:
                continue
            if e.status_ref is None:
                e.status_ref = e.actor.status.remote()
                continue
            done, _ = ray.wait([e.status_ref], timeout=0)
            if not done:
                continue
            ref, e.status_ref = e.status_ref, None
            try:
                e.status = ray.get(ref)
            except ray.exceptions.RayError as err:
                self._lost(e, err)

    def status(self) -> Status:
        """The ledger's counts with what the engines report (running, in flight, spend)."""
        status = self.tally.status()
        reports = [e.status for e in self.engines if "calls" in e.status]
        live = [e.status for e in self.engines if e.ready and "calls" in e.status]
        for r in live:
            for name, n in r["running"].items():
                model, track = name.split("/")
                if (model, track) in status.tracks:
                    status.tracks[(model, track)].running += n
        return with_reports(status, reports, live, "engines")

    # -- the end -------------------------------------------------------------------------------
    def _end(self, gracefully: bool) -> None:
        """Close the engines (or, interrupted, end them at once) and the limit board."""
        ray = self.ray
        live = [e for e in self.engines if not e.dead]
        now = time.monotonic()
        for e in self.engines:
            e.clock.end(now)
        if gracefully:
            closing = {e.actor.close.remote(): e for e in live if e.starting is None}
            with contextlib.suppress(Exception):
                ready, _ = ray.wait(list(closing), num_returns=len(closing), timeout=60)
                for ref in ready:
                    with contextlib.suppress(Exception):
                        closing[ref].final = ray.get(ref) or {}
        for e in live:
            with contextlib.suppress(Exception):
                ray.kill(e.actor, no_restart=True)
        if self.limiter is not None:
            with contextlib.suppress(Exception):
                ray.kill(self.limiter, no_restart=True)
        if self.engines:
            try:
                self._log_engine_time()
            except Exception:  # a report, never a reason to lose the sweep's own error
                log.exception("ray: the engines' time could not be reported")

    def engine_report(self) -> list[dict[str, Any]]:
        """Per engine: where it ran (its host and GPU ids), its seconds of start-up, working (a
        chunk or more) and waiting for work, the episodes it recorded, the chunks it was given
        (those of the critical path apart), whether it was its GPU's lead (the normal MPS
        priority of a ranked sweep), whether it died, and its GPU's busy share over its life and
        most memory (None where not sampled)."""
        now = time.monotonic()
        return [
            {
                "engine": e.index,
                "host": e.info.get("host"),
                "gpus": e.info.get("gpus"),
                **e.clock.figures(now),
                "episodes": e.clock.episodes,
                "chunks": len(e.given),
                "critical_chunks": [c.name for c in e.given if c.critical],
                "lead": e.lead,
                "died": e.dead,
                "gpu_busy": (e.final or e.status).get("gpu_busy"),
                "gpu_memory_mib": (e.final or e.status).get("gpu_memory_mib"),
            }
            for e in self.engines
        ]

    def _log_engine_time(self) -> None:
        report = self.engine_report()
        for r in report:
            gpu = f", GPU busy {r['gpu_busy']:.0%}" if r["gpu_busy"] is not None else ""
            log.info(
                "ray: engine %d (%s): start-up %.1f s, working %.1f s, waiting for work %.1f s, "
                "%d episodes%s%s",
                r["engine"],
                r["host"] or "not started",
                r["start_up_s"],
                r["working_s"],
                r["waiting_s"],
                r["episodes"],
                gpu,
                ", died" if r["died"] else "",
            )
        total = sum(r["life_s"] for r in report)
        if total > 0:
            log.info(
                "ray: engine time %.0f s over %d engines (%.0f s of sweep): start-up %.0f %%, "
                "working %.0f %%, waiting for work %.0f %%",
                total,
                len(report),
                time.monotonic() - self.started_at,
                100 * sum(r["start_up_s"] for r in report) / total,
                100 * sum(r["working_s"] for r in report) / total,
                100 * sum(r["waiting_s"] for r in report) / total,
            )


def _host(engine: EngineHandle) -> str:
    return f"engine {engine.index} ({engine.info.get('host', '?')})"


def _in_creation(err: BaseException) -> bool:
    return "error raised in its creation task" in str(err)


def _why(err: BaseException) -> str:
    """One line: the error an engine's creation raised (the last line of Ray's report), else
    the first line of Ray's."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    if not lines:
        return type(err).__name__
    return lines[-1] if _in_creation(err) else f"{type(err).__name__}: {lines[0]}"
