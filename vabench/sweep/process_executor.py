"""`executor: processes`: the sweep's (model, track, task) cells as worker processes of one host.

For many-core hosts where one sweep process is CPU-bound: C MuJoCo rollouts (one core per
process), a CPU-heavy embedded policy (the reference servo decodes and segments every image),
the learning stage's demonstration builds. The cells are those of `executor: ray`
(`ray_executor.pending_cells`) and each runs exactly as a Ray cell does (`run_cell`: a
`LocalSweep` restricted to the cell, with its own LLM pool, embedded server, render workers and
simulator batch, appending whole lines to the shared ledger under its file lock), so the records
equal those of the local executor. At most `executor.max_tasks` cells run at once, each in a
spawned process (never forked: the parent holds JAX and thread pools). A cell that raises is
logged with its traceback while the others run on; its episodes are listed as missing and a
rerun resumes them.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from vabench.config import SweepConfig
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.ray_executor import PROGRESS_EVERY_S, KeyTuple, pending_cells, recorded, run_cell
from vabench.sweep.results import LEDGER, Ledger, ledger_key

log = logging.getLogger(__name__)


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
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
        futures = {
            pool.submit(run_cell, document, str(run_dir), [ledger_key(k) for k in cell_keys]): cell
            for cell, cell_keys in cells.items()
        }
        pending = set(futures)
        while pending:
            done, pending = cf.wait(pending, timeout=PROGRESS_EVERY_S)
            for future in done:
                cell = futures[future]
                try:
                    summary = future.result()
                except Exception:
                    failures.append(cell)
                    log.exception("processes: cell %s failed", "/".join(cell))
                else:
                    log.info("processes: cell %s done: %s", "/".join(cell), summary)
            log.info(
                "processes: cells %d/%d done (%d failed) | episodes recorded %d/%d",
                len(futures) - len(pending),
                len(futures),
                len(failures),
                recorded(run_dir),
                len(keys),
            )
    if failures:
        log.error(
            "processes: %d of %d cells failed: %s",
            len(failures),
            len(cells),
            ", ".join("/".join(c) for c in failures),
        )
    return Ledger.open(run_dir).records
