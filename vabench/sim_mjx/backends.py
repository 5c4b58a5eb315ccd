"""The one edge where a physics backend is chosen.

    backend "c"                 C MuJoCo, slot by slot (`cpu.CpuBatch`): the oracle, and the
                                fastest path on a machine without an NVIDIA GPU.
    backend "mjx", impl "warp"  MuJoCo Warp on an NVIDIA GPU (`warp.batch.WarpBatch`): every
                                slot of a task in one captured CUDA graph per action.
    backend "mjx", impl "jax"   MJX on JAX (`mjx_batch.SimBatch`): CPU JAX for tests, TPUs.
    backend "auto"              "mjx"/"warp" where a CUDA GPU and the [gpu] extra are present,
                                else "c" (`resolve`, which also says why).

Asking for Warp where it cannot run gives one `BackendUnavailable` naming the missing package
or device. `VABENCH_WARP_DEVICE=cpu` runs the Warp backend on Warp's CPU device (slow: for tests
on machines without a GPU).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import mujoco

from vabench.sim_mjx.interface import BatchBase
from vabench.sim_mjx.warp.device import warp_device, warp_problem

BACKENDS = ("auto", "mjx", "c")
IMPLS = ("auto", "jax", "warp")


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
        from vabench.sim_mjx.warp.batch import WarpBatch

        kwargs.setdefault("device", warp_device())
        return WarpBatch(models, n_slots, **kwargs)
    from vabench.sim_mjx.mjx_batch import SimBatch

    return SimBatch(models, n_slots, **kwargs)
