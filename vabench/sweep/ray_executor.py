"""`executor: ray`: a sweep over a Ray cluster, one engine actor per GPU, the driver the only
writer of the ledger.

`run_ray(config, keys, run_dir)` is what `python -m vabench.sweep` calls for `kind: ray`:

1. the planned episodes not yet in results.jsonl are grouped into cells, one per (model, track,
   task), or, where engines batch their physics (Warp or MJX, `Physics.batched`), one per
   task (`cells.task_groups`: every track and model of a task in one simulator batch), and
   cut into chunks (`cells.chunks`, about `CHUNKS_PER_ENGINE` per engine, costliest first);
   when none is left nothing starts;
2. `ray.init(address=executor.address)` joins the cluster (`None`: the running local one if
   there is one, else a new local one; `"auto"`: the running one; `"HOST:PORT"`: that head
   node; Ray Client's `ray://` is refused by the config, as it cannot carry streaming actor
   calls); a driver that already called `ray.init` keeps its connection;
3. the engines (`ray_engine.EngineActor`, long-lived actors spread over the nodes): when the
   physics runs on GPUs (`simulator.backend` warp, mjx or auto on a cluster with GPUs:
   `choices.for_engines` decides what they run), by default 4 per GPU of the cluster
   (`ray_plan.engines_per_gpu`: where they can share it under CUDA MPS, else one), each
   running MuJoCo Warp and Warp's renderer for its chunks; otherwise one per
   `1 + render.workers` CPUs of the cluster, each claiming that many CPUs (C MuJoCo and the GL
   render workers: CPU-only nodes take these).
   `executor.actors` sets the number; more engines than GPUs each claim their share of one
   (`num_gpus` 1/k for k engines a GPU, told `VABENCH_GPU_SHARE`): several engine processes
   per GPU, each joining its node's CUDA MPS daemon of the sweep's (`mps.join_node_daemon`;
   not with `executor.mps: off`). When a model is not served by the embedded server, a
   limit board (`sweep.limiter.LimiterActor`, on the driver's node) keeps its RPM, TPM,
   concurrency and Retry-After pause for every engine at once;
4. the driver hands out chunks as engines have room (pull, `ray_plan.choose_engine`): a
   started engine is given the next chunk, the least loaded first, while its unfinished
   episodes are fewer than twice the in-flight limit it last reported, it runs fewer than
   `executor.max_tasks` chunks, and its load with the chunk stays within its fair share of the
   unfinished plan (engines still starting count: the first engine ready no longer takes
   every chunk); an engine without chunks always takes one, so a slow GPU or node is given
   less and holds nobody up; where engines share GPUs, a chunk of the critical path's task
   (the basket) goes to an idle engine, one a GPU where the engines allow, its GPU's one
   engine at the normal MPS priority (the others below it: `mps.NODE_RANKED`), and that engine
   takes nothing else until it is done; every engine compiles the sweep's Warp kernels as it
   starts;
5. each engine streams a chunk's ledger lines back as its episodes end; the driver appends them
   (`Ledger.append_line`, the only writer of results.jsonl and infrastructure.jsonl); a second
   record of an episode is refused and kept in results.duplicates.jsonl;
6. an engine that dies (its node lost, killed, out of memory) costs only its unfinished
   episodes: those of its chunks without a record go back to the front of the queue, the limit
   board frees its slots, and another engine is started in its place (at most
   `MAX_ENGINE_RESTARTS` in a sweep); an episode it finished without reporting it is adopted
   from its result.json where its chunk runs again;
7. a chunk that raises is logged with its traceback and the others run on (its episodes are
   listed as missing; the next invocation resumes them); a chunk stopped by an endpoint that
   refuses the sweep's requests (`LocalSweep.stopped`) ends the handing out: chunks in flight
   finish, and `run_ray` raises `SweepStopped`;
8. the driver logs a line when an engine starts or dies, when a chunk ends and every
   `PROGRESS_EVERY_S`, and at the end one per engine: its seconds of start-up, working (a
   chunk or more) and waiting for work, its episodes and its GPU's busy share (sampled by the
   engine, `gpu_busy`), then their sums; Ctrl-C ends every engine at once (no episode goes on
   calling a model);
9. the ledger's records are returned, `{(model, track, task, seed, run): record}`.

A killed driver takes its engines with it (Ray ends the actors a driver owns when the driver
exits): nothing writes the ledger after it, and the same command resumes from results.jsonl,
adopting the result.json of episodes that finished in the instant before.

The run directory must be one that every node sees at the same absolute path (a shared mount):
engines write the episodes' directories and the learning stage's summaries there, and refuse
to start where they cannot see the plan. The project is shipped from the driver's checkout
when `run_ray` connects to the cluster itself (`project_runtime_env`: the job's `working_dir`,
i.e. vabench, assets and configs, without run directories or caches); the nodes need the same
Python packages. API keys travel from the
driver's environment to the engines' in memory (`ray_engine`), never in a file.

`ray_plan` holds the engines' plan and the driver's bookkeeping, `ray_driver` the driver's
loop (`ClusterSweep`); their names are importable from here too.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from vabench.config import SweepConfig
from vabench.run_layout import RESULTS
from vabench.sweep.cells import KeyTuple, pending_cells
from vabench.sweep.choices import Choices
from vabench.sweep.display import Status
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.ray_driver import (
    ENGINE_START_TIMEOUT_S,
    MAX_ENGINE_RESTARTS,
    TICK_S,
    ClusterSweep,
)
from vabench.sweep.ray_plan import (
    CHUNKS_PER_ENGINE,
    SHIP_EXCLUDES,
    Chunk,
    EngineHandle,
    engine_environment,
    engine_plan,
    project_runtime_env,
    upload_failure,
)
from vabench.sweep.results import Ledger
from vabench.sweep.runner import SweepStopped

__all__ = [
    "CHUNKS_PER_ENGINE",
    "ENGINE_START_TIMEOUT_S",
    "MAX_ENGINE_RESTARTS",
    "SHIP_EXCLUDES",
    "TICK_S",
    "Chunk",
    "ClusterSweep",
    "EngineHandle",
    "engine_environment",
    "engine_plan",
    "project_runtime_env",
    "run_ray",
    "upload_failure",
]

log = logging.getLogger(__name__)


def run_ray(
    config: SweepConfig,
    keys: Sequence[EpisodeKey],
    run_dir: Path,
    choices: Choices,
    on_status: Callable[[Status], None] | None = None,
    on_engines: Callable[[list[dict[str, Any]]], None] | None = None,
) -> dict[KeyTuple, dict[str, Any]]:
    """Run the pending episodes of `keys` on the engines of a Ray cluster, for a sweep whose
    command chose `choices`, and return the ledger's records afterwards (see the module
    docstring). `on_status` is called about once a second; `on_engines` once at the end with
    `ClusterSweep.engine_report()` (each engine's time and GPU busy share)."""
    run_dir = Path(run_dir).resolve()  # engines start elsewhere: send an absolute path
    cells = pending_cells(keys, Ledger.open(run_dir).records)
    if not cells:
        log.info("ray: every planned episode is already in %s; nothing to run", RESULTS)
        return Ledger.open(run_dir).records

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
        sweep = ClusterSweep(ray, config, choices, keys, run_dir, cells, on_status)
        try:
            sweep.run()
        finally:
            if on_engines is not None:
                try:
                    on_engines(sweep.engine_report())
                except Exception:  # the caller's report must not hide the sweep's own error
                    log.exception("ray: on_engines failed")
    finally:
        if started_here:
            ray.shutdown()
    if sweep.failures:
        lost = sum(len(c.keys) for c in sweep.failures)
        log.error(
            "ray: %d chunks failed (%d episodes not run): %s",
            len(sweep.failures),
            lost,
            ", ".join(c.name for c in sweep.failures),
        )
    if sweep.stopped:
        raise SweepStopped(sweep.stopped[0])
    return Ledger.open(run_dir).records
