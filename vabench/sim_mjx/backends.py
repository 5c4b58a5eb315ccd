"""The one edge where a physics backend is chosen.

    backend "c"      C MuJoCo, slot by slot (`cpu.CpuBatch`): the oracle, and the fastest path
                     on a machine without an NVIDIA GPU.
    backend "warp"   MuJoCo Warp on an NVIDIA GPU (`warp.batch.WarpBatch`): every slot of a task
                     in one captured CUDA graph per action.
    backend "mjx"    MJX on JAX (`mjx_batch.SimBatch`): CPU JAX for tests, TPUs.
    backend "auto"   "warp" where a CUDA GPU and the [gpu] extra are present, else "c"
                     (`resolve`, which also says why).

The old spelling, backend "mjx" with impl "warp" or "jax", names the same backends
(`backend_name`; impl "auto" with "mjx" is read as "warp", what it picked on the hosts it was
written for). What was chosen is a `Choice` whose `kind` is a `Physics`: the rest of vabench
asks it (`batched`, `is_warp`, `jax_simulates`, `title`) instead of testing names, so this
module is the only one that reads or compares them (tests/test_layers.py checks that).

Asking for Warp where it cannot run gives one `BackendUnavailable` naming the missing package
or device. `VABENCH_WARP_DEVICE=cpu` runs the Warp backend on Warp's CPU device (slow: for tests
on machines without a GPU).
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import mujoco

from vabench.sim_mjx.warp.device import warp_device, warp_problem

if TYPE_CHECKING:  # choosing a backend (config, --dry-run) must not import JAX
    from vabench.sim_mjx.interface import BatchBase

BACKENDS = ("auto", "warp", "mjx", "c")
"""The names `simulator.backend` and `--backend` accept."""
IMPLS = ("auto", "jax", "warp")
"""The old second half of the name (`impl`, with backend "mjx"), still accepted."""


class BackendUnavailable(RuntimeError):
    """The requested physics backend cannot run on this machine; the message says why."""


class Physics(enum.Enum):
    """What steps a task's slots; the value is the backend's name."""

    C = "c"
    WARP = "warp"
    MJX_JAX = "mjx"

    @property
    def title(self) -> str:
        """How `--dry-run` names it."""
        return {"c": "C MuJoCo", "warp": "MuJoCo Warp", "mjx": "MJX on JAX"}[self.value]

    @property
    def batched(self) -> bool:
        """One batch steps every slot of a task on a device, for about the price of one slot
        (Warp, MJX on JAX): fill it rather than adapt (`tuning.inflight`), chunk by task."""
        return self is not Physics.C

    @property
    def is_warp(self) -> bool:
        return self is Physics.WARP

    @property
    def jax_simulates(self) -> bool:
        """JAX runs the physics, so JAX must see the accelerator (elsewhere JAX only runs
        small host-side functions and stays on the CPU)."""
        return self is Physics.MJX_JAX

    @property
    def backend(self) -> str:
        """The first half of the two-part name records carry ("c" or "mjx")."""
        return "c" if self is Physics.C else "mjx"

    @property
    def impl(self) -> str:
        """The second half ("warp" or "jax"; "-" for C)."""
        return {"c": "-", "warp": "warp", "mjx": "jax"}[self.value]

    @property
    def label(self) -> str:
        """The two-part name records and logs carry: "c", "mjx/warp", "mjx/jax"."""
        return "c" if self is Physics.C else f"mjx/{self.impl}"


@dataclass(frozen=True)
class Choice:
    """A resolved backend: what runs and why it was picked."""

    kind: Physics
    reason: str

    @property
    def batched(self) -> bool:
        return self.kind.batched

    @property
    def is_warp(self) -> bool:
        return self.kind.is_warp

    @property
    def jax_simulates(self) -> bool:
        return self.kind.jax_simulates

    @property
    def title(self) -> str:
        return self.kind.title

    @property
    def label(self) -> str:
        return self.kind.label


def backend_name(backend: str, impl: str | None = None) -> str:
    """The one-word name (`BACKENDS`) of `backend` with the old `impl`: "mjx" with impl "warp"
    (or "auto") is "warp", with impl "jax" (or none) "mjx"; with another backend impl says
    nothing, except that Warp is not MJX on JAX. Raises ValueError naming a bad value."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if impl is not None and impl not in IMPLS:
        raise ValueError(f"impl must be one of {IMPLS}, got {impl!r}")
    if backend == "mjx" and impl in ("warp", "auto"):
        return "warp"
    if backend == "warp" and impl == "jax":
        raise ValueError("impl jax contradicts backend warp (MJX on JAX is backend mjx)")
    return backend


def as_physics(backend: str | Physics, impl: str | None = None) -> Physics:
    """The backend an explicit name (not "auto") asks for; ValueError for any other."""
    if isinstance(backend, Physics):
        return backend
    name = backend_name(backend, impl)
    if name == "auto":
        raise ValueError("backend auto is a choice to make: resolve it first (`resolve`)")
    return Physics(name)


def resolve(
    backend: str = "auto",
    impl: str | None = None,
    device: str | None = None,
    *,
    probe: bool = True,
) -> Choice:
    """The backend that runs, with the reason (`device`: the Warp device, default
    `warp_device()`). Raises BackendUnavailable for an explicit request that cannot run here
    (never silently falls back). `probe=False`: decide for a device known to be an NVIDIA GPU
    without looking at this machine (a Ray sweep's engines, which `check` what they get)."""
    name = backend_name(backend, impl)
    if name == "c":
        return Choice(Physics.C, "C MuJoCo was asked for")
    if name == "mjx":
        return Choice(Physics.MJX_JAX, "MJX on JAX was asked for")
    device = device or warp_device()
    problem = warp_problem(device) if probe else None
    if name == "warp":
        if problem is not None:
            raise BackendUnavailable(problem)
        return Choice(Physics.WARP, f"MuJoCo Warp on {device}")
    if problem is None:
        return Choice(Physics.WARP, f"auto: MuJoCo Warp on {device}")
    # the reason alone: the fix it ends with ("Use backend c") is what auto just did
    return Choice(Physics.C, f"auto: {problem.split('. Use ')[0]}")


def check(physics: Physics, device: str | None = None) -> None:
    """Raise BackendUnavailable when `physics`, chosen elsewhere, cannot run here (Warp without
    its packages or its device); a check of a choice, never a new one."""
    if physics.is_warp:
        problem = warp_problem(device or warp_device())
        if problem is not None:
            raise BackendUnavailable(problem)


def make_batch(
    models: mujoco.MjModel | Sequence[mujoco.MjModel],
    n_slots: int,
    backend: str | Physics = "mjx",
    impl: str | None = None,
    **kwargs: Any,
) -> BatchBase:
    """A batch of `n_slots` episodes of the scene `models` on the named backend (`as_physics`:
    a `Physics`, or an explicit name). `kwargs` go to the backend's constructor (e.g. threads
    for C, lanes for JAX, nconmax for Warp)."""
    physics = as_physics(backend, impl)
    if physics is Physics.C:
        from vabench.sim_mjx.cpu import CpuBatch

        return CpuBatch(models, n_slots, **kwargs)
    if physics is Physics.WARP:
        from vabench.sim_mjx.warp.batch import WarpBatch

        kwargs.setdefault("device", warp_device())
        check(physics, kwargs["device"])
        return WarpBatch(models, n_slots, **kwargs)
    from vabench.sim_mjx.mjx_batch import SimBatch

    return SimBatch(models, n_slots, **kwargs)
