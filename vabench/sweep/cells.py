"""The sweep's plan cut into cells and chunks, and one cell run by itself.

A cell is the planned episodes of one (model, track, task) not yet in the ledger
(`pending_cells`); `chunks` cuts cells into pieces of nearly equal size so that the last
workers to finish do not leave the others idle. `executor: processes` runs each chunk in a
worker process with `run_cell` (a `LocalSweep` restricted to it, with its own LLM pool,
embedded server, render workers and simulator batch); `executor: ray` hands chunks to its
engine actors (`ray_engine`). `load_document` loads a config sent as a document
(`SweepConfig.document()`) in another process, naming the host when it does not load there.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import socket
import tempfile
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from vabench.config import SweepConfig, SweepConfigError, load_config
from vabench.run_layout import CONFIG, PLAN, RunDir
from vabench.sweep.board_socket import BoardAddress, joined
from vabench.sweep.choices import Choices
from vabench.sweep.display import status_of
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import Sink, ledger_key
from vabench.sweep.runner import LocalSweep, SweepProgress, open_engine

Cell = tuple[str, str, str]
"""(model, track, task)."""
KeyTuple = tuple[str, str, str, int, int]
"""(model, track, task, seed, run), as the ledger keys its records."""

PROGRESS_EVERY_S = 10.0
"""Seconds between an executor's log lines while no cell ends."""
STATUS = "status"
"""The name of a cell's status lines in its sink (`executor: processes`)."""
STATUS_EVERY_S = 1.0
WORKER_ENVIRONMENT = (
    "JAX_PLATFORMS",
    "XLA_PYTHON_CLIENT_PREALLOCATE",
    "CUDA_VISIBLE_DEVICES",
    "VABENCH_CORES",
    "CUDA_MPS_CLIENT_PRIORITY",
)
"""What a worker reports of its environment (the choices made for processes started on a GPU
host, `sweep.choices`)."""
MIN_CHUNK = 10
"""The fewest episodes a cell is cut down to: each chunk pays its own start-up."""
CHUNKS_PER_WORKER = 3


def pending_cells(
    keys: Iterable[EpisodeKey], finished: Iterable[KeyTuple]
) -> dict[Cell, list[EpisodeKey]]:
    """The planned episodes without a ledger record, grouped by (model, track, task), cells
    and episodes in plan order. Cells with nothing left are absent."""
    done = set(finished)
    cells: dict[Cell, list[EpisodeKey]] = {}
    for k in keys:
        if ledger_key(k) not in done:
            cells.setdefault((k.model, k.track, k.task), []).append(k)
    return cells


def task_groups(cells: Mapping[Cell, list[EpisodeKey]]) -> dict[tuple[str], list[EpisodeKey]]:
    """The cells of each task merged, every model and track, in plan order, keyed (task,).
    With batched physics a chunk runs as one simulator batch per task (`LocalSweep` groups its
    episodes by task), so chunks of whole tasks keep the batches large: on a GPU an action
    costs the same for 10 slots as for 200."""
    groups: dict[tuple[str], list[EpisodeKey]] = {}
    for (_, _, task), keys in cells.items():
        groups.setdefault((task,), []).extend(keys)
    return groups


def chunks(
    cells: Mapping[Any, list[EpisodeKey]],  # keyed by tuples of names: cells or task groups
    workers: int,
    cost: Callable[[str], int],
    per_worker: int = CHUNKS_PER_WORKER,
) -> list[tuple[str, list[EpisodeKey]]]:
    """The cells (or `task_groups`) cut into named chunks of nearly equal size, at least
    `per_worker` per worker where the cells are large enough (never below `MIN_CHUNK`
    episodes), costliest first (`cost(task)`: the task's step budget), so the workers finish
    close together. A chunk is named after its cell ("model/track/task", or "task" for a
    group; "... part i/n" when cut)."""
    total = sum(len(v) for v in cells.values())
    size = max(MIN_CHUNK, math.ceil(total / (workers * per_worker)))
    out = []
    for cell, keys in cells.items():
        parts = math.ceil(len(keys) / size)
        step = math.ceil(len(keys) / parts)
        for i, start in enumerate(range(0, len(keys), step), 1):
            name = "/".join(cell) + (f" part {i}/{parts}" if parts > 1 else "")
            out.append((name, keys[start : start + step]))
    return sorted(out, key=lambda c: -len(c[1]) * cost(c[1][0].task))


def bins(
    groups: Mapping[tuple[str], list[EpisodeKey]],
    workers: int,
    cost: Callable[[str], int],
) -> list[tuple[str, list[EpisodeKey]]]:
    """The `task_groups` dealt whole into at most `workers` chunks of nearly equal cost
    (longest first, each to the cheapest chunk so far; cost = episodes x `cost(task)`), for
    engine processes sharing one GPU (`executor: processes` with batched physics): each
    process then steps one batch per task of its chunk, all of them at once, as the local
    executor does for every task in one process. Several such processes on one GPU only pay
    where one process cannot keep the GPU busy (Python's interpreter lock: the sweep's "host:"
    lines) and with CUDA's multi-process service (else their contexts take turns). A chunk is
    named after its tasks, joined by '+'."""
    ranked = sorted(groups.items(), key=lambda kv: -len(kv[1]) * cost(kv[0][0]))
    n = max(1, min(workers, len(ranked)))
    loads = [0] * n
    members: list[list[tuple[tuple[str], list[EpisodeKey]]]] = [[] for _ in range(n)]
    for group, keys in ranked:
        i = loads.index(min(loads))
        loads[i] += len(keys) * cost(group[0])
        members[i].append((group, keys))
    dealt = sorted(
        (
            (load, "+".join(g[0] for g, _ in m), [k for _, keys in m for k in keys])
            for load, m in zip(loads, members, strict=True)
            if m
        ),
        key=lambda c: -c[0],
    )
    return [(name, keys) for _, name, keys in dealt]


def load_document(document: dict[str, Any], run_dir: Path) -> SweepConfig:
    """The config `document` (a `SweepConfig.document()`) loaded in this process, for the run
    directory `run_dir`, which must be the one the driver wrote its plan into (a shared mount
    on a cluster). Raises RuntimeError naming this host when either fails."""
    host = socket.gethostname()
    if not RunDir(run_dir).plan.exists():
        raise RuntimeError(
            f"{run_dir}: no {PLAN} here on {host}: executor: ray needs a run directory that "
            "every node sees at the same path (a shared mount)"
        )
    with tempfile.TemporaryDirectory(prefix="vabench-cell-") as tmp:
        path = Path(tmp) / CONFIG
        path.write_text(yaml.safe_dump(document, sort_keys=False), encoding="utf-8")
        try:
            return load_config(path)
        except SweepConfigError as err:
            raise RuntimeError(
                f"the sweep config does not load on {host}:\n"
                + str(err).replace(str(path), str(RunDir(run_dir).config))
            ) from None


def run_cell(
    document: dict[str, Any],
    choices: Choices,
    run_dir: str,
    keys: Sequence[KeyTuple],
    sink: Sink | None = None,
    board: BoardAddress | None = None,
) -> dict[str, Any]:
    """One cell, in a worker process: the episodes `keys` (all of one (model, track, task)) of
    the config `document` run by a `LocalSweep` into `run_dir`, on the sweep's `choices` (made
    by the parent, never again here). Returns counts for the log: host, episodes (run here),
    recorded (the cell's records in the ledger now), unscored, retried, what it ran on (the
    physics' label, the in-flight gate's reason) and the environment it ran in (JAX's
    platform, the variables of `WORKER_ENVIRONMENT`). With `sink`, ledger lines go there
    instead of the files (the parent writes them), with a `STATUS` line every second for the
    parent's display. With `board`, the cell's limits and spend caps are those of the sweep's
    limit board (`board_socket`), shared with every other worker."""
    run = Path(run_dir)
    config = load_document(document, run)
    sweep = LocalSweep(config, [EpisodeKey(*k) for k in keys], run, choices, ledger_sink=sink)
    model, track, task = keys[0][:3]
    report = None if sink is None else (lambda status: sink(STATUS, status_line(keys, status)))
    counts = asyncio.run(_run_reporting(sweep, report, board)).cells[(model, track, task)]
    import jax

    return {
        "host": socket.gethostname(),
        "episodes": len(keys),
        "recorded": counts.done,
        "unscored": counts.unscored,
        "retried": counts.retried,
        "stopped": sweep.stopped,
        "device_failed": sweep.device_failed,
        "physics": choices.physics.label,
        "in_flight": sweep.gate.reason if sweep.gate is not None else None,
        "jax": jax.default_backend(),
        "environment": {k: os.environ.get(k) for k in WORKER_ENVIRONMENT},
    }


async def _run_reporting(
    sweep: LocalSweep,
    report: Callable[[dict[str, Any]], None] | None,
    board: BoardAddress | None = None,
) -> SweepProgress:
    """`sweep.run()`, with `report(status)` every `STATUS_EVERY_S` and once at the end; with
    `board`, on an engine whose limits are the board's."""
    if board is not None:
        async with joined(board) as limits:
            opened = open_engine(
                sweep.config,
                sweep.choices,
                sweep.run_dir,
                shared_limits=limits,
                spend_caps=limits.spend,
            )
            async with opened as engine:
                return await _run_reporting_in(sweep, report, engine)
    return await _run_reporting_in(sweep, report, None)


async def _run_reporting_in(
    sweep: LocalSweep, report: Callable[[dict[str, Any]], None] | None, engine: Any
) -> SweepProgress:
    if report is None:
        return await sweep.run(engine)

    async def every_second() -> None:
        while True:
            report(cell_status(sweep.progress, finished=False))
            await asyncio.sleep(STATUS_EVERY_S)

    ticker = asyncio.create_task(every_second())
    try:
        return await sweep.run(engine)
    finally:
        ticker.cancel()
        report(cell_status(sweep.progress, finished=True))


def status_line(keys: Sequence[KeyTuple], status: dict[str, Any]) -> dict[str, Any]:
    """A worker's `STATUS` line for the chunk `keys` of one cell: the cell's name, and the
    chunk's (a cell may be cut into several chunks that run at once; the parent keeps the
    latest line of each chunk)."""
    model, track, task = keys[0][:3]
    cell = f"{model}/{track}/{task}"
    return {"cell": cell, "chunk": f"{cell}@{'/'.join(map(str, keys[0][3:]))}", **status}


def cell_status(progress: SweepProgress, finished: bool) -> dict[str, Any]:
    """What a worker reports of its sweep each second (`executor: processes`)."""
    status = status_of(progress)
    return {
        "finished": finished,
        "running": status.total().running,
        "in_flight": status.in_flight or 0,
        "limit": status.limit or 0,
        "reason": status.reason or "",
        "calls": status.calls,
        "tokens": status.tokens,
        "cost": status.cost,
        "calls_in_flight": status.calls_in_flight,
    }


def worker_logging(run: RunDir, name: int | str | None = None, console: Sequence[str] = ()) -> None:
    """Logging for a process the sweep started (a processes worker, a Ray engine): it starts
    with none, and its tasks' INFO lines (stage lines, "host:" lines, what the engine chose,
    the kernels' compilation) go to its own file in the run directory (`name`: its pid by
    default), its warnings to the console, and so do the INFO lines of the loggers named in
    `console` (a Ray engine's console is the driver's, prefixed with the actor)."""
    root = logging.getLogger()
    path = run.worker_log(os.getpid() if name is None else name)
    if any(getattr(h, "baseFilename", None) == os.path.abspath(path) for h in root.handlers):
        return  # set up already (an initializer run twice in one process)
    with contextlib.suppress(OSError):
        run.logs.mkdir(parents=True, exist_ok=True)
        to_file = logging.FileHandler(path, encoding="utf-8")
        to_file.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%H:%M:%S"))
        root.addHandler(to_file)
    if any(type(h) is logging.StreamHandler for h in root.handlers):
        root.setLevel(logging.INFO)
        return  # a console set up already (e.g. Ray's `logging_config`): lines once, not twice
    shown = tuple(console)

    def on_console(record: logging.LogRecord) -> bool:
        return record.levelno >= logging.WARNING or record.name.startswith(shown or "\0")

    to_console = logging.StreamHandler()
    to_console.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%H:%M:%S"))
    to_console.addFilter(on_console)
    root.addHandler(to_console)
    root.setLevel(logging.INFO)
