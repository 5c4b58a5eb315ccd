"""The one edge where a physics backend is chosen.

    backend "c"                 C MuJoCo, slot by slot (`cpu.CpuBatch`): the oracle, and the
                                fastest path on a machine without an NVIDIA GPU.
    backend "mjx", impl "warp"  MuJoCo Warp on an NVIDIA GPU (`warp_batch.WarpBatch`): every
                                slot of a task in one captured CUDA graph per action.
    backend "mjx", impl "jax"   MJX on JAX (`mjx_batch.SimBatch`): CPU JAX for tests, TPUs.
    backend "auto"              "mjx"/"warp" where a CUDA GPU and the [gpu] extra are present,
                                else "c" (`resolve`, which also says why).

Asking for Warp where it cannot run gives one `BackendUnavailable` naming the missing package
or device. `VABENCH_WARP_DEVICE=cpu` runs the Warp backend on Warp's CPU device (slow: for tests
on machines without a GPU).
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import mujoco

from vabench.sim_mjx.cuda_sync import prefer_blocking_sync
from vabench.sim_mjx.interface import BatchBase

BACKENDS = ("auto", "mjx", "c")
IMPLS = ("auto", "jax", "warp")
GPU_EXTRA = "pip install 'vabench[gpu]'"


class BackendUnavailable(RuntimeError):
    """The requested physics backend cannot run on this machine; the message says why."""


@dataclass(frozen=True)
class Choice:
    """A resolved backend: what runs and why it was picked."""

    backend: str  # "mjx" or "c"
    impl: str  # "jax" or "warp" ("-" for c)
    reason: str

    @property
    def label(self) -> str:
        return "c" if self.backend == "c" else f"mjx/{self.impl}"


GPU_SHARE = "VABENCH_GPU_SHARE"
"""Environment variable: how many processes share each GPU (set by the processes executor for
its workers). GPU buffers sized from the memory free (the Warp renderer's passes) take
1 / share of it, so that processes sizing at the same moment do not overcommit the card."""


def gpu_share() -> int:
    value = os.environ.get(GPU_SHARE, "1")
    return max(1, int(value)) if value.isdigit() else 1


def warp_device() -> str:
    """The Warp device the Warp backend uses: VABENCH_WARP_DEVICE, else the first CUDA GPU."""
    return os.environ.get("VABENCH_WARP_DEVICE", "cuda:0")


_DEVICE_LOCKS: dict[str, threading.RLock] = {}
_DEVICE_LOCKS_GUARD = threading.Lock()


def device_lock(device: str) -> threading.RLock:
    """The lock of one Warp device, held by whoever queues work on it (the physics batch for a
    whole action, the renderer for a whole pass). Warp queues every launch of a device on one
    stream, so the work of two threads could interleave: a render that reads a batch's state
    between two substeps of an action would see slots the action has not yet restored."""
    with _DEVICE_LOCKS_GUARD:
        return _DEVICE_LOCKS.setdefault(str(device), threading.RLock())


def warp_problem(device: str | None = None) -> str | None:
    """Why the Warp backend cannot run here (None when it can). Cheap: imports warp only when
    the packages are installed."""
    for module, package in (("warp", "warp-lang"), ("mujoco_warp", "mujoco-warp")):
        if importlib.util.find_spec(module) is None:
            return f"the Warp backend needs the package {package} ({GPU_EXTRA})"
    device = device or warp_device()
    prefer_blocking_sync()  # before wp.init makes the GPUs' contexts active
    import warp as wp

    wp.config.quiet = True  # type: ignore[attr-defined]  # not in warp's stubs
    wp.config.log_level = wp.LOG_WARNING  # no 'Module ... load' line per kernel module
    wp.init()
    if device.startswith("cuda"):
        if not wp.is_cuda_available():
            return (
                f"the Warp backend needs an NVIDIA GPU with a CUDA driver; Warp sees none "
                f"(devices: {', '.join(str(d) for d in wp.get_devices())}). Use backend c, or "
                "set VABENCH_WARP_DEVICE=cpu to run Warp on the CPU (slow)"
            )
        names = [str(d) for d in wp.get_cuda_devices()]
        if device != "cuda" and device not in names:
            return f"Warp device {device!r} does not exist (CUDA devices: {', '.join(names)})"
    elif device != "cpu":
        return f"VABENCH_WARP_DEVICE must be 'cpu' or 'cuda[:N]', got {device!r}"
    mjw_version = importlib.metadata.version("mujoco-warp")
    if mjw_version.split(".")[:2] != mujoco.__version__.split(".")[:2]:
        return (
            f"mujoco-warp {mjw_version} does not match mujoco {mujoco.__version__}: "
            f"install matching releases ({GPU_EXTRA})"
        )
    return None


def resolve(backend: str = "auto", impl: str = "auto", device: str | None = None) -> Choice:
    """The backend that runs, with the reason (`device`: the Warp device, default
    `warp_device()`). Raises BackendUnavailable for an explicit request that cannot run here
    (never silently falls back)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if impl not in IMPLS:
        raise ValueError(f"impl must be one of {IMPLS}, got {impl!r}")
    if backend == "c":
        return Choice("c", "-", "C MuJoCo was asked for")
    if backend == "mjx" and impl == "jax":
        return Choice("mjx", "jax", "MJX on JAX was asked for")
    device = device or warp_device()
    problem = warp_problem(device)
    if backend == "mjx":  # impl warp or auto
        if problem is None:
            return Choice("mjx", "warp", f"MuJoCo Warp on {device}")
        if impl == "warp":
            raise BackendUnavailable(problem)
        return Choice("mjx", "jax", f"MJX on JAX ({problem})")
    if problem is None:
        return Choice("mjx", "warp", f"auto: MuJoCo Warp on {device}")
    return Choice("c", "-", f"auto: C MuJoCo ({problem})")


def make_batch(
    models: mujoco.MjModel | Sequence[mujoco.MjModel],
    n_slots: int,
    backend: str = "mjx",
    impl: str = "jax",
    **kwargs: Any,
) -> BatchBase:
    """A batch of `n_slots` episodes of the scene `models` on the chosen backend. `kwargs` go
    to the backend's constructor (e.g. threads for C, lanes for JAX, nconmax for Warp)."""
    choice = resolve(backend, impl, kwargs.get("device") if impl == "warp" else None)
    if choice.backend == "c":
        from vabench.sim_mjx.cpu import CpuBatch

        return CpuBatch(models, n_slots, **kwargs)
    if choice.impl == "warp":
        from vabench.sim_mjx.warp_batch import WarpBatch

        kwargs.setdefault("device", warp_device())
        return WarpBatch(models, n_slots, **kwargs)
    from vabench.sim_mjx.mjx_batch import SimBatch

    return SimBatch(models, n_slots, **kwargs)
