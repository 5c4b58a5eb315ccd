"""The garbage collector's share of a long-lived process: what was built to last is frozen out
of its full collections.

Why: Python's cyclic collector walks every tracked object of the heap in a full collection,
with the interpreter lock held, so every thread of the process stops for it. An engine process
holds ~560,000 objects after importing Warp, MuJoCo Warp and JAX (~700,000 once a task batch is
built: ~0.3-0.4 s a full collection on this project's 2-core CPU, measured 2026-11-29), nearly
all of them kernels' code, modules and models that live as long as the process. On an H200 the
main job's engine processes each ran 9-15 full collections of 0.5-0.8 s (4.0-5.3 % of their
time; the basket's process 15, the longest 786 ms: each a stalled decision for every episode
of the process), docs/PERFORMANCE.md "Seventeenth session".

`freeze` collects what is garbage now and moves every surviving object to the collector's
permanent generation (`gc.freeze`): later collections walk only what was made after it. It is
called where a process has just built what it keeps: an engine process before its first
episode and after each task batch is built (kernels loaded, model on the device), a serving
process of the embedded server before it serves. Objects frozen are still freed by reference
counting; only a reference cycle that was alive at a freeze and becomes garbage afterwards is
never collected, which is why the calls sit at build points (episodes of other tasks may run
at a batch's build: their cycles, if any, stay until the process ends; bounded by the task
batches a process builds, ~6 in the main job). `VABENCH_GC_FREEZE=0` turns it off (to compare).

Only a process that says it is one of those (`own_process`: an engine worker, a Ray engine, a
serving process) freezes: the same sweep code also runs inside other programs (a test session
running many sweeps in its own process, a notebook), whose heaps are not ours to freeze.
"""

from __future__ import annotations

import gc
import logging
import os
import time

log = logging.getLogger(__name__)

FREEZE_VARIABLE = "VABENCH_GC_FREEZE"

_owned = False


def own_process() -> None:
    """This process is one of vabench's own long-lived workers: `freeze` acts in it."""
    global _owned
    _owned = True


def enabled() -> bool:
    return _owned and os.environ.get(FREEZE_VARIABLE, "1") != "0"


def freeze(after: str) -> int:
    """Collect, then freeze every tracked object (see the module docstring); returns how many
    objects are frozen now (0 when turned off, or in a process that is not vabench's own
    worker). `after` says what was just built (the log)."""
    if not enabled():
        return 0
    started = time.perf_counter()
    gc.collect()
    gc.freeze()
    frozen = gc.get_freeze_count()
    log.debug(
        "gc_freeze: %d objects frozen after %s (%.0f ms)",
        frozen,
        after,
        (time.perf_counter() - started) * 1000,
    )
    return frozen
