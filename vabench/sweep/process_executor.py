"""`executor: processes`: the sweep's (model, track, task) cells as worker processes of one host.

For many-core hosts where one sweep process is CPU-bound: C MuJoCo rollouts (one core per
process), a CPU-heavy embedded policy (the reference servo decodes and segments every image),
the learning stage's demonstration builds. The cells are those of `executor: ray`
(`ray_executor.pending_cells`) and each runs exactly as a Ray cell does (`run_cell`: a
`LocalSweep` restricted to the cell, with its own LLM pool, embedded server, render workers and
simulator batch), so the records equal those of the local executor. At most
`executor.max_tasks` cells run at once, each in a spawned process (never forked: the parent
holds JAX and thread pools). A cell that raises is logged with its traceback while the others
run on; its episodes are listed as missing and a rerun resumes them.

One writer, and no orphans: a worker never writes the ledger or the infrastructure log. It
writes its episodes' directories (result.json atomically, as always) and sends each log line to
the parent through a pipe; a thread of the parent appends them (`LedgerWriter`). Each worker
watches its parent and exits at once when the parent is gone (`_watch_parent`), so a SIGKILL of
the sweep's main process leaves no worker calling the model; an episode a worker finished in
the instant before is adopted from its result.json by the next invocation.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing
import os
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from vabench.config import SweepConfig
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.ray_executor import PROGRESS_EVERY_S, KeyTuple, pending_cells, recorded, run_cell
from vabench.sweep.results import LEDGER, Ledger, LedgerError, ledger_key
from vabench.sweep.runner import SweepStopped

log = logging.getLogger(__name__)

PARENT_CHECK_S = 0.2
"""How often a worker checks that its parent is alive."""

_lines: Any = None
"""In a worker: the pipe to the parent's `LedgerWriter` (set by `_init_worker`)."""


class LedgerWriter:
    """The parent's thread that appends the lines the workers send, in arrival order."""

    def __init__(self, run_dir: Path, lines: Any):
        self.ledger = Ledger.open(run_dir)
        self.lines = lines
        self.errors: list[str] = []
        self._thread = threading.Thread(target=self._run, name="ledger-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (item := self.lines.get()) is not None:
            name, record = item
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


def _init_worker(parent_pid: int, lines: Any) -> None:
    global _lines
    _lines = lines
    threading.Thread(
        target=_watch_parent, args=(parent_pid,), name="parent-watch", daemon=True
    ).start()


def _watch_parent(parent_pid: int) -> None:
    """Exit the worker as soon as its parent is gone (reparented: another parent pid). Its own
    children (render workers) see their pipes close and exit too."""
    while os.getppid() == parent_pid:
        time.sleep(PARENT_CHECK_S)
    os._exit(70)


def _send(name: str, record: dict[str, Any]) -> None:
    _lines.put((name, record))


def _run_cell_in_worker(
    document: dict[str, Any], run_dir: str, keys: Sequence[KeyTuple]
) -> dict[str, Any]:
    return run_cell(document, run_dir, keys, sink=_send)


def run_processes(
    config: SweepConfig, keys: Sequence[EpisodeKey], run_dir: Path
) -> dict[KeyTuple, dict[str, Any]]:
    """Run the pending episodes of `keys`, one process per cell, `executor.max_tasks` at once;
    return the ledger's records afterwards."""
    run_dir = Path(run_dir).resolve()
    cells = pending_cells(keys, Ledger.open(run_dir).records)
    if not cells:
        log.info("processes: every planned episode is already in %s; nothing to run", LEDGER)
        return Ledger.open(run_dir).records
    document = config.document()
    workers = min(config.executor.max_tasks, len(cells))
    log.info(
        "processes: %d cells (%d episodes), %d at once",
        len(cells),
        sum(len(v) for v in cells.values()),
        workers,
    )
    failures = []
    context = multiprocessing.get_context("spawn")
    lines = context.SimpleQueue()  # put() writes the pipe before returning: nothing buffered
    writer = LedgerWriter(run_dir, lines)
    try:
        with cf.ProcessPoolExecutor(
            max_workers=workers,
            mp_context=context,
            initializer=_init_worker,
            initargs=(os.getpid(), lines),
        ) as pool:
            futures = {
                pool.submit(
                    _run_cell_in_worker,
                    document,
                    str(run_dir),
                    [ledger_key(k) for k in cell_keys],
                ): cell
                for cell, cell_keys in cells.items()
            }
            pending = set(futures)
            stopped: list[str] = []
            while pending:
                done, pending = cf.wait(pending, timeout=PROGRESS_EVERY_S)
                done = {f for f in done if not f.cancelled()}
                for future in done:
                    cell = futures[future]
                    try:
                        summary = future.result()
                    except Exception:
                        failures.append(cell)
                        log.exception("processes: cell %s failed", "/".join(cell))
                    else:
                        log.info("processes: cell %s done: %s", "/".join(cell), summary)
                        if summary.get("stopped") and not stopped:
                            stopped.append(summary["stopped"])
                            for other in pending:  # cells not started yet never start
                                other.cancel()
                log.info(
                    "processes: cells %d/%d done (%d failed) | episodes recorded %d/%d",
                    len(futures) - len(pending),
                    len(futures),
                    len(failures),
                    recorded(run_dir),
                    len(keys),
                )
    finally:
        writer.close()
    if failures:
        log.error(
            "processes: %d of %d cells failed: %s",
            len(failures),
            len(cells),
            ", ".join("/".join(c) for c in failures),
        )
    if stopped:
        raise SweepStopped(stopped[0])
    return Ledger.open(run_dir).records
