"""`executor: processes`: the sweep's cells as worker processes of one host.

For many-core hosts where one sweep process is CPU-bound: C MuJoCo rollouts (one core per
process), a CPU-heavy embedded policy (the reference servo decodes and segments every image),
the learning stage's demonstration builds. The cells
(`cells.pending_cells`, one per (model, track, task)) are cut into chunks so that the last
processes to finish do not leave the others' cores idle (`cells.chunks`); with batched physics
(Warp, MJX) whole tasks are dealt over the workers instead, each worker stepping one batch per
task of its chunk, all at once (`cells.bins`, `plan_chunks`): engine processes sharing a GPU,
for a process bound by Python's interpreter lock (with CUDA MPS; without it their contexts
take turns on the GPU). Each chunk runs in
`cells.run_cell` (a `LocalSweep` restricted to it, with its own LLM pool, embedded server,
render workers and simulator batch, on the sweep's `Choices`, sent to it as they are), so the
records equal those of the local executor.
At most `executor.max_tasks` run at once, each in a spawned process (never forked: the parent
holds JAX and thread pools). A chunk that raises is logged with its traceback while the others
run on; its episodes are listed as missing and a rerun resumes them. A worker that dies (out of
memory, a crash in native code) breaks the whole pool: new workers take up the chunks it took
down, up to `MAX_POOL_RESTARTS` times (an H100 run lost 46 of 72 chunks to one nvJPEG abort
before this).

One limit board for every worker (`limiter.LimitBoard`, served by the parent on a local
socket, `board_socket`): the RPM, TPM and concurrency of each endpoint not served by the
embedded server (each worker's embedded server keeps its own), Retry-After pauses, and the
spend caps, so N workers send what the config allows, not N times it, and a cap holds exactly.
A worker that dies gives back what it held when its connection closes.

The workers' environment (`choices.child_environment`): JAX never preallocates GPU memory and
stays on the CPU unless the physics is MJX on JAX; with several GPUs each worker gets one; each
worker's `VABENCH_CORES` is its share of the host's cores, which its pools are sized to
(`children.usable_cores`: policy processes of its embedded server, JPEG threads).

One writer, and no orphans: a worker never writes the ledger or the infrastructure log. It
writes its episodes' directories (result.json atomically, as always) and sends each log line to
the parent through a pipe, with a status line every second (episodes running, in flight, model
calls, tokens, cost) for the display; a thread of the parent appends the lines
(`LedgerWriter`). Each worker watches its parent and exits at once when the parent is gone
(`children.exit_with_parent`), so a SIGKILL of the sweep's main process leaves no worker
calling the model; an episode a worker finished in the instant before is adopted from its
result.json by the next invocation. Ctrl-C (`sweep.interrupt`): workers ignore it; the parent
ends them, keeps every whole line they sent, and raises `Interrupted`.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import cProfile
import dataclasses
import functools
import logging
import math
import multiprocessing
import os
import re
import threading
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

from vabench.children import (
    CORES_VARIABLE,
    children_ignore_sigint,
    exit_with_parent,
    ignore_sigint,
    process_age_s,
    started_with,
)
from vabench.config import SweepConfig
from vabench.run_layout import RESULTS, RunDir
from vabench.sim_mjx.warp.device import GPU_SHARE, warp_device
from vabench.sweep.board_socket import BoardAddress, BoardServer
from vabench.sweep.cells import (
    PROGRESS_EVERY_S,
    STATUS,
    WORKER_ENVIRONMENT,
    KeyTuple,
    bins,
    chunks,
    pending_cells,
    run_cell,
    task_groups,
    worker_logging,
)
from vabench.sweep.choices import Choices, child_environment, gpu_for_worker
from vabench.sweep.display import Status, Tally, with_reports
from vabench.sweep.limiter import LimitBoard, shared_endpoints
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import Ledger, LedgerError, ledger_key
from vabench.sweep.runner import SweepStopped, critical_path_tasks, spend_caps
from vabench.tasks import REGISTRY
from vabench.tuning import kernel_profile, mps, precompile

log = logging.getLogger(__name__)

TICK_S = 1.0
"""How often the parent redraws the display."""
MAX_POOL_RESTARTS = 3
"""Times the workers are started again after one of them died (each death takes down every
chunk the pool was running: concurrent.futures marks the whole pool broken)."""

PROFILE_VARIABLE = "VABENCH_PROFILE_DIR"
"""Set to a folder: every worker writes there a cProfile of each chunk it runs
(`<pid>-<first episode>.prof`), of its event loop's thread: the engine, the model client, an
embedded server in its process, the agent's decisions. For hosts with no sampling profiler,
such as the lent GPU machines (`MAIN_PROFILE=1 bash benchmarks/gpu/run.sh main`)."""

_lines: Any = None
"""In a worker: the pipe to the parent's `LedgerWriter` (set by `_init_worker`)."""


class LedgerWriter:
    """The parent's thread that appends the lines the workers send, in arrival order, and keeps
    their latest status lines."""

    def __init__(self, run_dir: Path, lines: Any):
        self.ledger = Ledger.open(run_dir)
        self.lines = lines
        self.errors: list[str] = []
        self.statuses: dict[str, dict[str, Any]] = {}
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ledger-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            while self.lines.empty():  # SimpleQueue.get has no timeout
                if self._stopping.is_set():
                    return
                time.sleep(0.05)
            item = self.lines.get()
            if item is None:
                return
            name, record = item
            if name == STATUS:
                self.statuses[record["chunk"]] = record
                continue
            try:
                self.ledger.append_line(name, record)
            except (LedgerError, OSError, KeyError, ValueError) as err:
                self.errors.append(str(err))
                log.error("processes: a worker's %s line was not written: %s", name, err)

    def close(self) -> None:
        """Wait for every line sent so far: the workers have returned, so their lines are in
        the pipe ahead of this sentinel."""
        self.lines.put(None)
        self._thread.join()

    def abandon(self) -> None:
        """After the workers were ended: append what is in the pipe, then stop (without the
        sentinel: a worker ended while writing to the pipe may hold its lock)."""
        self._stopping.set()
        self._thread.join(timeout=10)

    def status(self, tally: Tally) -> Status:
        """The ledger's counts with what the workers report (running, in flight, spend)."""
        status = tally.status()
        reports = list(self.statuses.values())
        live = [r for r in reports if not r["finished"]]
        for r in live:
            model, track = r["cell"].split("/")[:2]
            if (model, track) in status.tracks:
                status.tracks[(model, track)].running += r["running"]
        return with_reports(status, reports, live, "worker processes")


def _init_worker(
    parent_pid: int, lines: Any, counter: Any, gpus: tuple[str, ...], run_dir: str
) -> None:
    global _lines
    ignore_sigint()  # the parent ends this process (vabench.children)
    _lines = lines
    worker_logging(RunDir(Path(run_dir)))
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    gpu = gpu_for_worker(index, gpus)
    if gpu is not None:  # before anything here initialises CUDA
        os.environ["CUDA_VISIBLE_DEVICES"] = gpu
    # gone with its parent; its own children (render workers) see their pipes close and exit
    exit_with_parent(parent_pid)


def _send(name: str, record: dict[str, Any]) -> None:
    _lines.put((name, record))


def _run_cell_in_worker(
    document: dict[str, Any],
    choices: Choices,
    run_dir: str,
    keys: Sequence[KeyTuple],
    environment: Mapping[str, str] | None = None,
    board: BoardAddress | None = None,
) -> dict[str, Any]:
    # Before anything here makes a CUDA context, which reads the MPS client priority: with
    # batched physics every chunk is submitted at once, one a worker, but the pool does not
    # promise it (a worker whose chunk failed at once may take another): then say so. Put
    # back afterwards, so that a later chunk of this process runs as the sweep's others.
    global _chunks_run
    environment = dict(environment or {})
    age = process_age_s()
    if not _chunks_run and age is not None:  # the spawn's start: its interpreter and imports
        log.info("engine process: its first chunk %.1f s after the process started", age)
    if environment and _chunks_run:
        log.warning(
            "processes: the critical path's chunk runs in a worker that ran %d chunk(s) before: "
            "its CUDA context exists, so its MPS priority is that of the others",
            _chunks_run,
        )
    _chunks_run += 1
    with started_with(environment):
        return _run_chunk(document, choices, run_dir, keys, board)


_chunks_run = 0
"""Chunks this worker process was given (`_run_cell_in_worker`)."""


def _run_chunk(
    document: dict[str, Any],
    choices: Choices,
    run_dir: str,
    keys: Sequence[KeyTuple],
    board: BoardAddress | None,
) -> dict[str, Any]:
    kernel_profile.record_in_background()  # where VABENCH_KERNEL_PROFILE asks for it
    folder = os.environ.get(PROFILE_VARIABLE)
    if not folder:
        return run_cell(document, choices, run_dir, keys, sink=_send, board=board)
    profile = cProfile.Profile()
    profile.enable()
    try:
        return run_cell(document, choices, run_dir, keys, sink=_send, board=board)
    finally:
        profile.disable()
        Path(folder).mkdir(parents=True, exist_ok=True)
        first = re.sub(r"[^\w.-]+", "_", "-".join(map(str, keys[0])))
        profile.dump_stats(Path(folder) / f"{os.getpid()}-{first}.prof")


def _end_workers(pool: cf.ProcessPoolExecutor) -> None:
    """Terminate the pool's processes (`terminate_workers` arrives in Python 3.14)."""
    processes = list((pool._processes or {}).values())
    for p in processes:
        with contextlib.suppress(Exception):
            p.terminate()
    for p in processes:
        p.join(timeout=10)


def plan_chunks(
    config: SweepConfig, cells: dict[Any, list[EpisodeKey]], choices: Choices
) -> list[tuple[str, list[EpisodeKey]]]:
    """The chunks the workers take. With batched physics (Warp, MJX: an action costs the same
    for 10 slots as for 200) whole tasks, every track and model, dealt over the workers, each
    stepping one batch per task at once (several engine processes sharing a GPU, `cells.bins`);
    else cells cut to keep every core busy to the end (`cells.chunks`). The task's step budget
    is its cost (a task the registry lacks fails in its chunk).

    With batched physics and several workers sharing GPUs under MPS, a task on the sweep's
    critical path (`runner.critical_path_tasks`: the basket's 250 steps against 50) gets an
    engine process of its own beside them: its episodes take ~166 decisions to the others'
    13-37, every decision waits for the process's other batches, and on an H100 its 60
    episodes were the last unfinished at 332 s while four engine processes had recorded the
    other 2,100 by 302 s (docs/PERFORMANCE.md, "Fifth session")."""

    cost = functools.partial(_cost, config)
    workers = choices.executor.max_tasks
    if not choices.physics.batched:
        return chunks(cells, min(workers, len(cells)), cost)
    groups = task_groups(cells)
    critical = critical_tasks(config, cells, choices)
    alone = [(task, keys) for (task,), keys in groups.items() if task in critical]
    rest = {group: keys for group, keys in groups.items() if group[0] not in critical}
    return alone + (bins(rest, workers, cost) if rest else [])


def _cost(config: SweepConfig, task: str) -> int:
    """A task's cost for dealing the plan: its step budget (a task the registry lacks fails in
    its chunk)."""
    return config.budget(task) if task in REGISTRY else 1


def plan_critical_path(
    config: SweepConfig, cells: dict[Any, list[EpisodeKey]], choices: Choices
) -> set[str]:
    """The tasks of `cells` on the whole sweep's critical path (`runner.critical_path_tasks`)
    where physics is batched (each worker is told it: `for_chunk`); none otherwise."""
    if not choices.physics.batched:
        return set()
    return critical_path_tasks({k[0]: _cost(config, k[0]) for k in task_groups(cells)})


def critical_tasks(
    config: SweepConfig, cells: dict[Any, list[EpisodeKey]], choices: Choices
) -> set[str]:
    """The critical path's tasks that get an engine process of their own (`plan_chunks`), run
    ahead of the others (`critical_environment`): where engine processes share GPUs under MPS
    (batched physics, several workers). Without MPS (one engine process per GPU): none."""
    ex = choices.executor
    if not (ex.mps and ex.max_tasks > 1):
        return set()
    return plan_critical_path(config, cells, choices)


def worker_shares(choices: Choices, workers: int) -> dict[str, str]:
    """The variables that size each of `workers` worker processes to its share: of its GPU
    (`GPU_SHARE`: render passes) and of the host's cores (`CORES_VARIABLE`: the embedded
    server's processes, JPEG threads). The critical path's process of its own (`plan_chunks`)
    is not counted: its ~60 episodes need a fraction of what a quarter of the GPU's 1,024 do,
    and counting it cut every worker of a 16-core H100 host from 4 cores to 3, below the 4 from
    which the embedded server has processes of its own: the reference agent's replies were
    then computed in the engine processes, and the warm suite slowed from 2,100 episodes at
    248 s to 1,765 at 330 s (2026-11-27)."""
    sharing = max(1, min(workers, choices.executor.max_tasks))
    gpus = max(1, len(choices.machine.gpus))
    return {
        GPU_SHARE: str(math.ceil(sharing / gpus)),
        CORES_VARIABLE: str(max(1, choices.machine.cores // sharing)),
    }


def for_chunk(
    choices: Choices, part: Sequence[EpisodeKey], critical: Collection[str] = ()
) -> Choices:
    """The choices a worker runs `part` on: with batched physics (a chunk of whole tasks,
    `cells.bins`) every task of its chunk at once, one batch each, and the sweep's critical
    path as the parent decided it (`critical`, `plan_critical_path`: a worker sees only its own
    tasks, and among a chunk's 200-step place_cube_on_cube and 50-step others it would find
    one); else the sweep's."""
    ex = choices.executor
    if not choices.physics.batched:
        return choices
    tasks = len({k.task for k in part})
    decided = tuple(sorted(critical))
    if tasks <= ex.max_tasks and decided == ex.critical_path:
        return choices
    return dataclasses.replace(
        choices,
        executor=dataclasses.replace(ex, max_tasks=max(tasks, ex.max_tasks), critical_path=decided),
    )


def critical_environment(
    choices: Choices, shared: Mapping[str, str], part: Sequence[EpisodeKey], critical: set[str]
) -> dict[str, str]:
    """What the worker of `part` sets before it starts, beyond the environment `shared` by all
    workers: for the critical path's process (a chunk of `critical` tasks), the MPS priority of
    a normal client while every other worker's is below normal (`mps.PRIORITY_VARIABLE`), and
    half the host's cores (`CORES_VARIABLE`: its embedded server's processes, JPEG threads;
    its ~60 episodes' replies of a decision round were computed by 2 processes at ~32 ms each,
    up to ~1 s on the critical path; docs/PERFORMANCE.md, "Seventh session"). Nothing for the
    other workers."""
    if not critical or not {k.task for k in part} <= critical:
        return {}
    cores = max(int(shared.get(CORES_VARIABLE, "1")), choices.machine.cores // 2)
    return {mps.PRIORITY_VARIABLE: mps.NORMAL, CORES_VARIABLE: str(cores)}


def _start_board(
    stack: contextlib.ExitStack, config: SweepConfig, run_dir: Path
) -> BoardAddress | None:
    """The sweep's limit board, served to the workers until `stack` closes: the limits of
    every endpoint not served by the embedded server, and the spend caps over what `run_dir`
    already spent. None when there is nothing to keep."""
    limits = shared_endpoints(config.models, config.embedded_models)
    caps = spend_caps(config, run_dir)
    if not limits and caps is None:
        return None
    server = BoardServer(LimitBoard(limits, caps))
    address = server.start()
    stack.callback(server.close)
    kept = [f"the limits of {', '.join(limits)}"] if limits else []
    kept += ["the spend caps"] if caps is not None else []
    log.info("processes: one limit board for every worker keeps %s", " and ".join(kept))
    return BoardAddress(address, tuple(limits), caps is not None)


def _gpu_sharing(stack: contextlib.ExitStack, choices: Choices) -> dict[str, str]:
    """Where engine processes share a GPU: an MPS daemon of the sweep's own for them (closed
    with `stack`), and the variables that make the workers its clients. Without it they still
    run, their contexts taking turns on the GPU (logged)."""
    if not choices.executor.mps:
        return {}
    try:
        return stack.enter_context(mps.private_daemon())
    except mps.MpsUnavailable as err:
        log.warning(
            "CUDA MPS could not start (%s): the %d engine processes' CUDA contexts take turns "
            "on the GPU, slower than under MPS (executor.mps: off runs one engine process per "
            "GPU)",
            err,
            choices.executor.max_tasks,
        )
        return {}


def _precompile(
    config: SweepConfig, parts: Sequence[tuple[str, Sequence[EpisodeKey]]], choices: Choices
) -> precompile.Compiling | None:
    """Warp physics on a GPU: every family's kernels compiled once, here, in the background
    (`precompile.Compiling`), started before the workers: each worker's families wait for
    their own kernels (a worker compiling them would compile, one worker after another under
    the machine's lock, the modules the families share). Returns once the compile holds the
    machine's lock; with `VABENCH_WARP_PRECOMPILE=first`, once it has ended (the workers then
    start after it, as before the overlap)."""
    if not choices.physics.is_warp or not warp_device().startswith("cuda"):
        return None
    tasks = sorted({k.task for _, part in parts for k in part})
    render = config.render
    size = (render.width, render.height)
    first = (
        critical_path_tasks({t: _cost(config, t) for t in tasks})
        if choices.physics.batched
        else set()
    )
    compiling = precompile.Compiling.start(
        tasks, *size, warp_device(), choices.renderer.is_warp, first
    )
    if os.environ.get(precompile.ENV) == "first":
        compiling.join()
    return compiling


def run_processes(
    config: SweepConfig,
    keys: Sequence[EpisodeKey],
    run_dir: Path,
    choices: Choices,
    on_status: Callable[[Status], None] | None = None,
) -> dict[KeyTuple, dict[str, Any]]:
    """Run the pending episodes of `keys` in worker processes, the chosen executor's
    `max_tasks` at once (batched physics: every chunk of `plan_chunks` at once), on `choices`;
    return the ledger's records afterwards. `on_status` is called about once a second."""
    run_dir = Path(run_dir).resolve()
    cells = pending_cells(keys, Ledger.open(run_dir).records)
    if not cells:
        log.info("processes: every planned episode is already in %s; nothing to run", RESULTS)
        return Ledger.open(run_dir).records
    machine = choices.machine
    parts = plan_chunks(config, cells, choices)
    # batched physics: every chunk at once (`plan_chunks` makes at most `max_tasks`, plus the
    # critical path's own)
    workers = len(parts) if choices.physics.batched else min(choices.executor.max_tasks, len(parts))
    env = child_environment(choices.physics) | worker_shares(choices, workers)
    critical = critical_tasks(config, cells, choices)  # in a process of its own
    if critical:  # every engine process below the critical path's on the GPU
        env[mps.PRIORITY_VARIABLE] = mps.BELOW_NORMAL
    decided = plan_critical_path(config, cells, choices)  # told to every worker
    seen = {k: v for k in WORKER_ENVIRONMENT if (v := env.get(k, os.environ.get(k))) is not None}
    log.info(
        "processes: %d cells (%d episodes) in %d chunks, %d at once; workers run with %s%s",
        len(cells),
        sum(len(v) for v in cells.values()),
        len(parts),
        workers,
        " ".join(f"{k}={v}" for k, v in seen.items()) or "this environment",
        f", one of GPUs {','.join(machine.gpus)} each" if len(machine.gpus) > 1 else "",
    )
    document = config.document()
    tally = Tally(run_dir, keys)
    failures: list[str] = []
    stopped: list[str] = []
    context = multiprocessing.get_context("spawn")
    lines = context.SimpleQueue()  # put() writes the pipe before returning: nothing buffered
    writer = LedgerWriter(run_dir, lines)
    pool: cf.ProcessPoolExecutor | None = None
    finished = False
    todo = list(parts)
    restarts = 0
    device_stop: str | None = None  # why a worker's GPU context failed, this pool
    gpu = contextlib.ExitStack()
    compiling: precompile.Compiling | None = None
    try:
        # before the daemon: this process is no client (its CUDA context is made first). The
        # compile's children, started about now, may be the daemon's clients or not: each runs
        # a few launches (a GPU in exclusive-process mode would refuse the latter: their
        # families then compile in the workers on first use, as after any child's failure).
        compiling = _precompile(config, parts, choices)
        board = _start_board(gpu, config, run_dir)
        clients = _gpu_sharing(gpu, choices)
        env.update(clients)
        worker_gpus = machine.gpus
        if clients:  # the sweep's own daemon numbers the GPUs it sees 0..n-1
            devices, worker_gpus = mps.client_devices(machine.gpus)
            env.update(devices)
        while todo:
            with started_with(env), children_ignore_sigint():
                pool = cf.ProcessPoolExecutor(
                    max_workers=workers,
                    mp_context=context,
                    initializer=_init_worker,
                    initargs=(
                        os.getpid(),
                        lines,
                        context.Value("i", 0),
                        worker_gpus,
                        str(run_dir),
                    ),
                )
                futures = {
                    pool.submit(
                        _run_cell_in_worker,
                        document,
                        for_chunk(choices, part, decided),
                        str(run_dir),
                        [ledger_key(k) for k in part],
                        critical_environment(choices, env, part, critical),
                        board,
                    ): (name, part)
                    for name, part in todo
                }
            todo = []
            pending = set(futures)
            last_log = time.monotonic()
            while pending:
                done, pending = cf.wait(pending, timeout=TICK_S)
                for future in (f for f in done if not f.cancelled()):
                    name, part = futures[future]
                    try:
                        summary = future.result()
                    except cf.process.BrokenProcessPool:
                        todo.append((name, part))  # a worker died: every chunk of the pool
                        continue
                    except Exception:
                        failures.append(name)
                        log.exception("processes: cell %s failed", name)
                        continue
                    log.info("processes: cell %s done: %s", name, summary)
                    if summary.get("device_failed"):  # a new process has a new context
                        device_stop = summary["stopped"]
                        todo.append((name, part))
                        for other in pending:  # not started: the new workers take them (below)
                            other.cancel()
                        continue
                    if summary.get("stopped") and not stopped:
                        stopped.append(summary["stopped"])
                        for other in pending:  # chunks not started yet never start
                            other.cancel()
                tally.refresh()
                if on_status is not None:
                    on_status(writer.status(tally))
                if done or time.monotonic() - last_log >= PROGRESS_EVERY_S:
                    last_log = time.monotonic()
                    log.info(
                        "processes: cells %d/%d done (%d failed) | episodes recorded %d/%d",
                        len(parts) - len(pending) - len(todo),
                        len(parts),
                        len(failures),
                        tally.status().total().done,
                        len(keys),
                    )
            pool.shutdown(wait=True)
            if stopped:  # an endpoint refused, or a cap: nothing more starts
                todo = []
            elif device_stop is not None:  # cancelled once above, whatever cancel() said after
                todo.extend(futures[f] for f in futures if f.cancelled())
            if todo and restarts >= MAX_POOL_RESTARTS:
                if device_stop is not None:
                    stopped.append(device_stop)
                else:
                    failures.extend(name for name, _ in todo)
                log.error(
                    "processes: a worker process died or lost its GPU %d times; %d chunks not run",
                    restarts + 1,
                    len(todo),
                )
                todo = []
            elif todo:
                restarts += 1
                log.warning(
                    "processes: %s; starting new workers for the %d chunks it took down "
                    "(recorded episodes are kept, interrupted ones restart)",
                    f"a worker's GPU failed ({device_stop})"
                    if device_stop is not None
                    else "a worker process died (killed, out of memory, or a crash in native "
                    "code: its last lines are above)",
                    len(todo),
                )
                device_stop = None
        finished = True
    finally:
        if finished:
            if pool is not None:
                pool.shutdown()
            writer.close()
        else:  # interrupted (or failed): end the workers, keep every whole line they sent
            if pool is not None:
                _end_workers(pool)
                pool.shutdown(wait=True, cancel_futures=True)
            writer.abandon()
        gpu.close()  # the MPS daemon quits once its clients, the workers, are gone; the board
        if compiling is not None:  # long over unless the sweep was: its children end theirs
            compiling.join(timeout=precompile.CHILD_TIMEOUT_S if finished else 0)
    if failures:
        log.error(
            "processes: %d of %d cells failed: %s", len(failures), len(parts), ", ".join(failures)
        )
    if stopped:
        raise SweepStopped(stopped[0])
    return Ledger.open(run_dir).records
