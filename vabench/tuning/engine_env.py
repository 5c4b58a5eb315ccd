"""The environment of the processes a sweep starts for its engines, for every executor.

JAX never preallocates GPU memory (XLA_PYTHON_CLIENT_PREALLOCATE=false: 16 worker processes
that each took 75 % of one GPU lost most of their episodes) and stays on the CPU unless the
physics is MJX on JAX (JAX_PLATFORMS=cpu: C MuJoCo and Warp use JAX only for small host-side
functions): `child_environment`, applied to the sweep's own process by `configure_jax`. The
switches travel as the parent reads them. Each engine is sized to its share of the cores
(`CORES_VARIABLE`: its embedded server's processes, JPEG threads) and of its GPU (`GPU_SHARE`:
GPU buffers sized from the memory free), given one GPU where several are visible
(`gpu_for_worker`), and placed under CUDA MPS where engines share a GPU: worker processes as
clients of the sweep's own daemon (`shared_gpu_clients`), the critical path's one at the normal
priority and the others below it (`critical_path_environment`); Ray engines joining their
node's daemon (`ray_environment`, `mps.join_node_daemon`). Values the user set are kept.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
from collections.abc import Iterable, Mapping

from vabench import switches
from vabench.children import CORES_VARIABLE
from vabench.sim_mjx.backends import Choice
from vabench.sim_mjx.warp.device import GPU_SHARE
from vabench.tuning import mps

log = logging.getLogger(__name__)

REPORTED = (
    "JAX_PLATFORMS",
    "XLA_PYTHON_CLIENT_PREALLOCATE",
    "CUDA_VISIBLE_DEVICES",
    CORES_VARIABLE,
    mps.PRIORITY_VARIABLE,
)
"""What an engine reports of its environment (its start line, the driver's log)."""


def child_environment(physics: Choice, environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """The JAX variables (see the module docstring) not already set in `environ`, and the
    switches' variables as this process reads them (`vabench.switches.environment`: those of a
    value other than the default), so that the sweep's children read the same."""
    wanted = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    if not physics.jax_simulates:
        wanted["JAX_PLATFORMS"] = "cpu"
    own = switches.environment(switches.current(environ))
    return {k: v for k, v in wanted.items() if k not in environ} | own


def configure_jax(physics: Choice) -> None:
    """Apply `child_environment` to this process; JAX reads these when it first creates a
    backend, which nothing in the sweep has done before its choices are made. JAX's cache and
    matmul precision are set again from the switches (`sim_mjx.jax_setup`, imported before
    the config's switches were in the environment)."""
    env = child_environment(physics)
    os.environ.update(env)
    from vabench.sim_mjx import jax_setup

    jax_setup.configure()
    if "JAX_PLATFORMS" in env:
        import jax

        jax.config.update("jax_platforms", env["JAX_PLATFORMS"])


def gpu_for_worker(index: int, gpus: tuple[str, ...]) -> str | None:
    """The GPU worker process `index` uses when several are visible (round robin); None when
    there are fewer than two (nothing to spread)."""
    return gpus[index % len(gpus)] if len(gpus) > 1 else None


def shares(cores: int, gpu_share: int) -> dict[str, str]:
    """The variables that size an engine to `cores` cores and a GPU shared by `gpu_share`."""
    return {GPU_SHARE: str(max(1, gpu_share)), CORES_VARIABLE: str(max(1, cores))}


def worker_shares(cores: int, gpus: int, engines: int) -> dict[str, str]:
    """Each of `engines` worker processes' share of `cores` host cores and of `gpus` GPUs."""
    engines = max(1, engines)
    return shares(cores // engines, math.ceil(engines / max(1, gpus)))


def critical_path_environment(shared_cores: int, host_cores: int) -> dict[str, str]:
    """The worker process of the critical path's tasks, where the others run with
    `shared_cores` each below the normal MPS priority: a normal client, with half the host's
    cores (its embedded server's replies are on the critical path; docs/PERFORMANCE.md)."""
    cores = max(shared_cores, host_cores // 2)
    return {mps.PRIORITY_VARIABLE: mps.NORMAL, CORES_VARIABLE: str(cores)}


def shared_gpu_clients(stack: contextlib.ExitStack, engines: int) -> dict[str, str]:
    """An MPS daemon of the sweep's own for `engines` worker processes sharing GPUs (closed
    with `stack`), and the variables that make them its clients. Without it they still run,
    their contexts taking turns on the GPU (logged)."""
    try:
        return stack.enter_context(mps.private_daemon())
    except mps.MpsUnavailable as err:
        log.warning(
            "CUDA MPS could not start (%s): the %d engine processes' CUDA contexts take turns "
            "on the GPU, slower than under MPS (executor.mps: off runs one engine process per "
            "GPU)",
            err,
            engines,
        )
        return {}


def engines_per_gpu(mps_setting: str = "auto") -> int:
    """Ray engines a GPU when `executor.actors` is unset: `mps.ENGINES_PER_GPU` where they can
    share it under CUDA MPS (`mps_setting`, the config's `executor.mps`, is auto and NVIDIA's
    control program is on this node, which stands for the cluster's: nodes of one image; an
    engine on a node without it warns and its GPU's engines take turns), else one."""
    if mps_setting == "auto" and mps.control_program() is not None:
        return mps.ENGINES_PER_GPU
    return 1


def ray_environment(
    cores: int,
    gpu_share: int = 1,
    sweep: str = "",
    ranked: bool = False,
    keys: Iterable[str] = (),
) -> dict[str, str]:
    """What a Ray engine's process is started with: the switches as this process reads them,
    its share of its node's cores and, where engines share a GPU, of the GPU and, with the
    sweep's id `sweep` (`executor.mps` not off), `mps.NODE_SWEEP`: the engines of a node join
    one MPS daemon of the sweep's; `ranked` (the sweep has critical chunks) adds
    `mps.NODE_RANKED`, one engine a GPU a normal client for them, the others below. The API
    keys named by `keys` travel from this process's environment, in memory."""
    env = switches.environment(switches.current()) | {CORES_VARIABLE: str(max(1, cores))}
    if gpu_share > 1:
        env |= shares(cores, gpu_share)
        if sweep:
            env[mps.NODE_SWEEP] = sweep
            if ranked:
                env[mps.NODE_RANKED] = "1"
    env |= {name: os.environ[name] for name in keys if name and os.environ.get(name)}
    return env
