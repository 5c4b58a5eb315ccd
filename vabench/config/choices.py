"""What a sweep runs on: the fastest path this machine offers, chosen once, with the reasons.

    physics    simulator.backend auto: MuJoCo Warp on a CUDA GPU with the [gpu] extra, else
               C MuJoCo (`sim_mjx.backends.resolve`)
    renderer   render.backend auto: Warp's ray tracer on such a GPU, else the GL worker
               processes (`render.backends.resolve_renderer`)
    executor   executor.kind auto: with MuJoCo Warp, `processes` of `mps.ENGINES_PER_GPU`
               engine processes per GPU under a CUDA MPS daemon of the sweep's own where
               NVIDIA's MPS control program is installed (`executor.mps`); without MPS
               `local` (one process, every task batch at once) on one GPU and one engine
               process per GPU on several; else `processes` (one cell per core at once) on
               a host of `PROCESSES_FROM_CORES` cores or more, else `local`
    in flight  executor.in_flight auto: adapts to what the machine and endpoints sustain
               (`tuning.inflight`)

`choose` makes them once per sweep command, into one `Choices`: `--dry-run` prints its lines,
the sweep logs them when it starts, and every executor receives it (the local one, the worker
processes of `processes`, pickled, and a Ray sweep's driver, which sends its engines the
choices `for_engines` makes for the cluster's GPUs): nothing downstream resolves an `auto`
again. `VABENCH_CORES` tells the choices how many cores to size for (default: the CPUs this
process may run on); the test suite pins it so that its sweeps run the same way on any machine.

The environment of the processes the sweep starts is `tuning.engine_env`'s.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

from vabench import switches
from vabench.children import usable_cores, visible_gpus
from vabench.config.schema import ExecutorOptions, SweepConfig
from vabench.llm_pool.server_config import serving_description
from vabench.render.backends import RenderChoice, resolve_renderer
from vabench.sim_mjx.backends import Choice, resolve
from vabench.switches import Effective
from vabench.tuning import mps
from vabench.tuning.inflight import InFlightRule, in_flight_rule

PROCESSES_FROM_CORES = 4
"""From this many cores on, `executor: auto` runs cells in worker processes: below it the
parent, one cell process and its render workers would share too few cores to gain."""
LOCAL_MAX_TASKS = 4
"""Task batches at once in one process (`executor: local`)."""
RAY_MAX_TASKS = 16
"""Chunks at once in one engine actor of a Ray sweep (the in-flight rule binds first)."""
GPU_LOCAL_MAX_TASKS = 64
"""Task batches at once in the one process of `executor: auto` on a GPU (configs/all.yaml has
22): every batch of the plan steps on the GPU, none waits for another to finish."""
ONE_GPU_REASON = (
    "auto: Warp physics on one GPU, no CUDA MPS (executor.mps: off, or nvidia-cuda-mps-control "
    "not installed): one process steps every task's batch (faster than a worker process per "
    "core, whose CUDA contexts take turns on the GPU)"
)
MPS_REASON = (
    "auto: Warp physics on {gpus}: {per_gpu} engine processes share each GPU under a CUDA MPS "
    "daemon of the sweep's own ({cores} cores each), whole task families dealt over them by "
    "cost, a task on the critical path (the basket) in one more of its own; one process is "
    "paced by its host side (docs/PERFORMANCE.md, 'Engine processes on one GPU')"
)
MULTI_GPU_REASON = (
    "auto: Warp physics on {n} GPUs: one engine process per GPU ({cores} cores each), whole "
    "task families dealt over them by cost, each stepping its tasks' batches as one process "
    "does on one GPU (a process per core would put several CUDA contexts on each GPU, taking "
    "turns)"
)


@dataclass(frozen=True)
class Machine:
    cores: int
    gpus: tuple[str, ...]
    """Visible CUDA devices (ids as CUDA_VISIBLE_DEVICES names them)."""
    cores_from: str = "CPUs this process may use"
    mps: bool = False
    """NVIDIA's MPS control program is installed (`tuning.mps`)."""

    def describe(self) -> str:
        n = len(self.gpus)
        gpus = f"{n} GPU{'s' if n != 1 else ''}" if n else "no GPU"
        return f"{self.cores} cores ({self.cores_from}), {gpus}"


def this_machine(environ: Mapping[str, str] = os.environ) -> Machine:
    cores, gpus = usable_cores(environ), visible_gpus(environ)
    has_mps = bool(gpus) and mps.control_program() is not None
    if switches.is_set("cores", environ):
        return Machine(cores, gpus, switches.variable("cores"), mps=has_mps)
    return Machine(cores, gpus, mps=has_mps)


@dataclass(frozen=True)
class ExecutorChoice:
    kind: str  # local | processes | ray
    max_tasks: int
    reason: str
    mps: bool = False
    """The processes executor runs a CUDA MPS daemon for its workers (`tuning.mps`)."""
    per_gpu: int = 1
    """Engine processes sharing each GPU (processes executor, batched physics on GPUs)."""
    critical_path: tuple[str, ...] | None = None
    """The tasks on the whole sweep's critical path, decided by the processes executor for its
    workers and by the Ray driver for its engines (each sees only its chunk's tasks); None: a
    `LocalSweep` decides from the budgets of its own tasks (`sweep.cells.critical_path_tasks`)."""

    @property
    def label(self) -> str:
        unit = {"local": "task batches", "processes": "cells", "ray": "chunks per engine"}
        shared = f", {self.per_gpu} per GPU under CUDA MPS" if self.mps else ""
        return f"{self.kind}, {self.max_tasks} {unit[self.kind]} at once{shared}"


def resolve_executor(
    options: ExecutorOptions, machine: Machine, physics: Choice | None = None
) -> ExecutorChoice:
    """`options`: the config's; `physics`: the resolved simulator. Spend
    caps do not matter here: the limit board keeps them for every process."""
    kind, max_tasks = options.kind, options.max_tasks
    warp = physics is not None and physics.is_warp
    gpus = len(machine.gpus)
    use_mps = warp and gpus > 0 and machine.mps and options.mps == "auto"
    if kind == "auto" and use_mps:
        engines = max_tasks or mps.ENGINES_PER_GPU * gpus
        per_gpu = math.ceil(engines / gpus)
        reason = MPS_REASON.format(
            gpus="one GPU" if gpus == 1 else f"{gpus} GPUs",
            per_gpu=per_gpu,
            cores=max(1, machine.cores // engines),
        )
        return ExecutorChoice("processes", engines, reason, mps=per_gpu > 1, per_gpu=per_gpu)
    if kind == "auto" and warp and gpus <= 1:
        return ExecutorChoice("local", max_tasks or GPU_LOCAL_MAX_TASKS, ONE_GPU_REASON)
    if kind == "auto" and warp:
        return ExecutorChoice(
            "processes",
            max_tasks or gpus,
            MULTI_GPU_REASON.format(n=gpus, cores=machine.cores // gpus),
        )
    if kind == "auto":
        if machine.cores >= PROCESSES_FROM_CORES:
            return ExecutorChoice(
                "processes",
                max_tasks or machine.cores,
                f"auto: {machine.cores} cores: cells in worker processes, one per core",
            )
        return ExecutorChoice(
            "local",
            max_tasks or LOCAL_MAX_TASKS,
            f"auto: {machine.cores} cores: one process (worker processes pay off from "
            f"{PROCESSES_FROM_CORES} cores)",
        )
    default = {"local": LOCAL_MAX_TASKS, "processes": machine.cores, "ray": RAY_MAX_TASKS}[kind]
    if kind == "processes" and use_mps:  # engine processes, not one per core
        default = mps.ENGINES_PER_GPU * gpus
    chosen = ExecutorChoice(kind, max_tasks or default, "asked for")
    if kind == "processes" and use_mps and chosen.max_tasks > gpus:
        per_gpu = math.ceil(chosen.max_tasks / gpus)
        return replace(
            chosen,
            reason=f"asked for; {per_gpu} engine processes share each GPU under CUDA MPS",
            mps=True,
            per_gpu=per_gpu,
        )
    return chosen


@dataclass(frozen=True)
class Choices:
    """What a sweep runs on, chosen once (`choose`) and passed to every executor."""

    machine: Machine
    physics: Choice
    renderer: RenderChoice
    executor: ExecutorChoice
    in_flight: InFlightRule
    model_server: str | None = None
    """Where the embedded server works, when a model uses it."""
    switches: Effective = field(default_factory=lambda: Effective({}))
    """The `VABENCH_*` switches the sweep runs with (`vabench.switches.resolve`)."""

    def lines(self) -> list[str]:
        overrides = self.switches.overrides()
        switched = f"{', '.join(overrides)}: the environment over the config"
        return [
            f"machine:   {self.machine.describe()}",
            f"physics:   {self.physics.title} ({self.physics.reason})",
            f"renderer:  {self.renderer.title} ({self.renderer.reason})",
            f"executor:  {self.executor.label} ({self.executor.reason})",
            f"in flight: {self.in_flight.describe()}",
            *([f"server:    {self.model_server}"] if self.model_server else []),
            *([f"switches:  {switched}"] if overrides else []),
        ]


def choose(
    config: SweepConfig,
    machine: Machine | None = None,
    environ: Mapping[str, str] = os.environ,
    effective: Effective | None = None,
) -> Choices:
    """Resolve every `auto` of `config` (a `SweepConfig`) for this machine, and its switches
    against `environ` (unless `effective` says them). Raises
    `sim_mjx.backends.BackendUnavailable` (its message naming what is missing) when the config
    asks explicitly for a backend that cannot run here."""
    machine = machine or this_machine(environ)
    ex = config.executor
    effective = effective or switches.resolve(config.switch_values(), environ)
    device = effective.values["warp_device"]
    physics = resolve(config.simulator.backend, device=device)
    in_flight = in_flight_rule(ex.in_flight, ex.max_episodes, physics.batched)
    executor = resolve_executor(ex, machine, physics)
    if executor.per_gpu > 1 and physics.batched:  # the GPU's episodes shared by its engines
        in_flight = in_flight_rule(
            ex.in_flight, max(1, ex.max_episodes // executor.per_gpu), physics.batched
        )
    server = None
    if config.embedded_models and executor.kind == "ray":
        server = "embedded, in each engine, sized to the engine's share of its node's cores"
    elif config.embedded_models:
        # a worker process of `processes` sizes its server to its share of the cores
        share = machine.cores if executor.kind == "local" else machine.cores // executor.max_tasks
        share = max(1, share)
        where = "the sweep's process has" if executor.kind == "local" else "each worker has"
        server = (
            f"embedded, {serving_description(config.embedded_server, share)} ({where} "
            f"{share} core{'s' if share != 1 else ''})"
        )
    renderer = resolve_renderer(config.render.backend, device)
    return Choices(machine, physics, renderer, executor, in_flight, server, effective)


def apply_switches(config: SweepConfig) -> Effective:
    """The switches of `config` (a `SweepConfig`) against this process's environment, then
    set in it (where it sets none of its own: `vabench.switches.apply`), so that this process
    and every process it starts read the sweep's values. Called by the sweep's parent before
    `choose(config, effective=...)`: its first Warp call fixes how the process's threads wait
    for the GPU, and which switches the environment overrode is read before they are set."""
    effective = switches.resolve(config.switch_values())
    switches.apply(effective.values)
    return effective


ENGINE_GPU = "each engine's GPU"
"""The device a Ray sweep's GPU engines are decided for (each claims one; CUDA numbers it 0)."""


def for_engines(choices: Choices, config: SweepConfig, gpus: int) -> Choices:
    """The choices the engines of a Ray sweep run with, on a cluster of `gpus` GPUs (known once
    the driver has joined it). Where the physics asked for batches (`auto`, `warp`, `mjx`) and
    the cluster has GPUs, each engine claims one, and its physics, renderer and in-flight rule
    are decided for that GPU by the rules that made `choices` (`probe=False`: the driver cannot
    look at another node's GPU; an engine checks what it is given when it starts). Otherwise
    the engines run on CPUs as `choices` says (every node has the driver's packages)."""
    if gpus < 1:
        return choices
    physics = resolve(config.simulator.backend, device=ENGINE_GPU, probe=False)
    if not physics.batched:  # C MuJoCo asked for: CPU engines
        return choices
    ex = config.executor
    return replace(
        choices,
        physics=physics,
        renderer=resolve_renderer(config.render.backend, ENGINE_GPU, probe=False),
        in_flight=in_flight_rule(ex.in_flight, ex.max_episodes, physics.batched),
    )
