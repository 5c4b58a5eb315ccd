"""`executor: ray`: the sweep's (model, track, task) cells as Ray tasks over a cluster.

`run_ray(config, keys, run_dir)` is what `python -m vabench.sweep` calls for `kind: ray`:

1. the planned episodes not yet in the ledger (`results.jsonl`) are grouped into cells, one per
   (model, track, task), in plan order (`pending_cells`); when none is left nothing starts;
2. `ray.init(address=executor.address)` joins the cluster (`None`: the running local one if
   there is one, else a new local one; `"auto"`: the running one; `"HOST:PORT"`: that head
   node); a driver that already called `ray.init` keeps its connection;
3. each cell is one Ray task (`run_cell`): a worker process loads the config from its
   `document()`, builds a `LocalSweep` restricted to the cell's episodes and runs it with
   asyncio: its own LLM pool, embedded server (when a model uses one), render pool and
   simulator batch, writing episode directories and ledger lines into the shared run
   directory. Cells are disjoint, so no episode runs twice; the ledger's appends are whole
   lines under a file lock (`vabench.sweep.results`), so several writers never mix lines;
4. at most `executor.max_tasks` cells (default 4) are in flight at once; each claims 1 CPU
   from Ray's scheduler (its render workers, `render.workers` processes, are not counted)
   and, for the `mjx` or `auto` backend on a cluster with GPUs, 1 GPU;
5. the driver logs a progress line when a cell ends and every `PROGRESS_EVERY_S` seconds
   (cells done / total, episodes in `results.jsonl` / planned); a cell that raises is logged
   with its cell, host and remote traceback, and the other cells still run to the end;
6. the ledger is read again and its records returned, `{(model, track, task, seed, run):
   record}`; episodes of failed cells are simply missing (the command lists them, and running
   it again resumes them).

The run directory must be one directory that every node sees at the same absolute path (an
NFS or other shared mount): `run_cell` refuses to start where it cannot see the plan the
driver wrote there. API-key variables are read on the worker's node (they must be set in the
environment of each node's Ray processes); a config that does not load there fails the cell,
naming the node.

Ray retries a cell whose worker process died (Ray's default `max_retries`); the retry resumes
from the ledger like a rerun of the command does. Application errors are not retried. A cell
stopped by an endpoint that refuses the sweep's requests (`LocalSweep.stopped`) ends the
submitting: the cells in flight finish, none starts, and `run_ray` raises `SweepStopped`.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import yaml

from vabench.config import SweepConfig, SweepConfigError, load_config
from vabench.sweep.choices import RAY_MAX_TASKS
from vabench.sweep.display import Status, Tally, status_of
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import LEDGER, Ledger, Sink, ledger_key
from vabench.sweep.runner import LocalSweep, SweepProgress, SweepStopped

log = logging.getLogger(__name__)

Cell = tuple[str, str, str]
"""(model, track, task)."""
KeyTuple = tuple[str, str, str, int, int]
"""(model, track, task, seed, run), as the ledger keys its records."""

PROGRESS_EVERY_S = 10.0
"""Seconds between log lines while no cell ends."""
TICK_S = 1.0
"""Seconds between display updates."""
STATUS = "status"
"""The name of a cell's status lines in its sink (`executor: processes`)."""
STATUS_EVERY_S = 1.0
WORKER_ENVIRONMENT = (
    "JAX_PLATFORMS",
    "XLA_PYTHON_CLIENT_PREALLOCATE",
    "CUDA_VISIBLE_DEVICES",
    "VABENCH_CORES",
)
"""What a cell reports of its environment (the choices made for processes started on a GPU
host, `sweep.choices`)."""


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


def cell_resources(config: SweepConfig, cluster_gpus: float) -> dict[str, float]:
    """What one cell asks Ray's scheduler for (see the module docstring, 4)."""
    # backend auto picks Warp on a node with a GPU: claim one there as mjx does
    gpus = 1.0 if config.simulator.backend != "c" and cluster_gpus >= 1 else 0.0
    return {"num_cpus": 1.0, "num_gpus": gpus}


def run_cell(
    document: dict[str, Any],
    run_dir: str,
    keys: Sequence[KeyTuple],
    sink: Sink | None = None,
) -> dict[str, Any]:
    """One cell, in a Ray worker: the episodes `keys` (all of one (model, track, task)) of the
    config `document` (a `SweepConfig.document()`) run by a `LocalSweep` into `run_dir`.
    Returns counts for the driver's log: host, episodes (run here), recorded (the cell's
    records in the ledger now), unscored, retried, and the environment it ran in (JAX's
    platform, the variables of `WORKER_ENVIRONMENT`). With `sink`, ledger lines go there
    instead of the files (`executor: processes`: the parent writes them), with a `STATUS` line
    every second for the parent's display."""
    host = socket.gethostname()
    run = Path(run_dir)
    if not (run / "plan.json").exists():
        raise RuntimeError(
            f"{run}: no plan.json here on {host}: executor: ray needs a run directory that "
            "every node sees at the same path (a shared mount)"
        )
    with tempfile.TemporaryDirectory(prefix="vabench-cell-") as tmp:
        path = Path(tmp) / "sweep.yaml"
        path.write_text(yaml.safe_dump(document, sort_keys=False), encoding="utf-8")
        try:
            config = load_config(path)
        except SweepConfigError as err:
            raise RuntimeError(
                f"the sweep config does not load on {host}:\n"
                + str(err).replace(str(path), str(run / "sweep.yaml"))
            ) from None
    sweep = LocalSweep(config, [EpisodeKey(*k) for k in keys], run, ledger_sink=sink)
    model, track, task = keys[0][:3]
    cell = f"{model}/{track}/{task}"
    report = None if sink is None else (lambda status: sink(STATUS, {"cell": cell, **status}))
    counts = asyncio.run(_run_reporting(sweep, report)).cells[(model, track, task)]
    import jax

    return {
        "host": host,
        "episodes": len(keys),
        "recorded": counts.done,
        "unscored": counts.unscored,
        "retried": counts.retried,
        "stopped": sweep.stopped,
        "jax": jax.default_backend(),
        "environment": {k: os.environ.get(k) for k in WORKER_ENVIRONMENT},
    }


async def _run_reporting(
    sweep: LocalSweep, report: Callable[[dict[str, Any]], None] | None
) -> SweepProgress:
    """`sweep.run()`, with `report(status)` every `STATUS_EVERY_S` and once at the end."""
    if report is None:
        return await sweep.run()

    async def every_second() -> None:
        while True:
            report(_cell_status(sweep.progress, finished=False))
            await asyncio.sleep(STATUS_EVERY_S)

    ticker = asyncio.create_task(every_second())
    try:
        return await sweep.run()
    finally:
        ticker.cancel()
        report(_cell_status(sweep.progress, finished=True))


def _cell_status(progress: SweepProgress, finished: bool) -> dict[str, Any]:
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


def run_ray(
    config: SweepConfig,
    keys: Sequence[EpisodeKey],
    run_dir: Path,
    on_status: Callable[[Status], None] | None = None,
) -> dict[KeyTuple, dict[str, Any]]:
    """Run the pending episodes of `keys` as Ray tasks, one per cell, and return the ledger's
    records afterwards (see the module docstring). `on_status` is called about once a second
    with the ledger's counts, read as it grows."""
    run_dir = Path(run_dir).resolve()  # workers may start elsewhere: send an absolute path
    cells = pending_cells(keys, Ledger.open(run_dir).records)
    if not cells:
        log.info("ray: every planned episode is already in %s; nothing to run", LEDGER)
        return Ledger.open(run_dir).records

    import ray  # the `ray` extra; only this executor needs it

    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=config.executor.address)
    stopped: list[str] = []
    try:
        tally = Tally(run_dir, keys)
        failures = _run_cells(ray, config, cells, tally, run_dir, stopped, on_status)
    finally:
        if started_here:
            ray.shutdown()
    if failures:
        lost = sum(len(cells[c]) for c in failures)
        log.error(
            "ray: %d of %d cells failed (%d episodes not run): %s",
            len(failures),
            len(cells),
            lost,
            ", ".join("/".join(c) for c in failures),
        )
    if stopped:
        raise SweepStopped(stopped[0])
    return Ledger.open(run_dir).records


def _run_cells(
    ray: Any,
    config: SweepConfig,
    cells: dict[Cell, list[EpisodeKey]],
    tally: Tally,
    run_dir: Path,
    stopped: list[str],
    on_status: Callable[[Status], None] | None,
) -> dict[Cell, BaseException]:
    """Submit the cells, at most `executor.max_tasks` in flight, and wait for all of them;
    returns the failed cells with their errors. A cell stopped by a refusing endpoint
    (appended to `stopped`) ends the submitting: cells in flight finish, no new one starts.
    Interrupted (Ctrl-C), the cells in flight are cancelled, their workers ended."""
    resources = cell_resources(config, ray.cluster_resources().get("GPU", 0))
    remote = ray.remote(run_cell).options(**resources)
    document = config.document()
    limit = config.executor.max_tasks or RAY_MAX_TASKS
    log.info(
        "ray: %d cells (%d episodes) on a cluster of %s; %d cells at once, each %s",
        len(cells),
        sum(len(v) for v in cells.values()),
        {k: v for k, v in ray.cluster_resources().items() if k in ("CPU", "GPU")},
        limit,
        resources,
    )
    queue = list(cells)
    in_flight: dict[Any, Cell] = {}
    failures: dict[Cell, BaseException] = {}
    done = 0
    last_log = time.monotonic()
    try:
        while queue or in_flight:
            while queue and len(in_flight) < limit and not stopped:
                cell = queue.pop(0)
                keys = [ledger_key(k) for k in cells[cell]]
                in_flight[remote.remote(document, str(run_dir), keys)] = cell
            ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=TICK_S)
            done += _collect(ray, ready, in_flight, failures, stopped, queue)
            tally.refresh()
            if on_status is not None:
                on_status(tally.status())
            if ready or time.monotonic() - last_log >= PROGRESS_EVERY_S:
                last_log = time.monotonic()
                log.info(
                    "ray: cells %d/%d done (%d failed), %d running | episodes recorded %d/%d",
                    done,
                    len(cells),
                    len(failures),
                    len(in_flight),
                    tally.status().total().done,
                    len(tally.planned),
                )
    except BaseException:  # Ctrl-C: no cell of this sweep goes on calling the model
        for ref in in_flight:
            ray.cancel(ref, force=True)
        raise
    return failures


def _collect(
    ray: Any,
    ready: list[Any],
    in_flight: dict[Any, Cell],
    failures: dict[Cell, BaseException],
    stopped: list[str],
    queue: list[Cell],
) -> int:
    """Take the results of the `ready` cells; returns how many ended."""
    for ref in ready:
        cell = in_flight.pop(ref)
        try:
            summary = ray.get(ref)
        except Exception as err:  # the cell's own error, wrapped by Ray with its traceback
            failures[cell] = err
            log.error("ray: cell %s failed:\n%s", "/".join(cell), err)
        else:
            log.info("ray: cell %s done on %s: %s", "/".join(cell), summary["host"], summary)
            if summary.get("stopped"):
                stopped.append(summary["stopped"])
                queue.clear()
    return len(ready)
