"""The Warp device this process uses, whether Warp can run on it, and who may queue work on it.

`warp_problem` says why the Warp backend cannot run here (None when it can): a missing
package, no CUDA GPU, a mujoco-warp release that does not match mujoco. `warp_device` is the
device both the physics batches and the renderer use (VABENCH_WARP_DEVICE, else cuda:0);
`device_lock` the lock of that device; `gpu_share` how many processes share each GPU.
"""

from __future__ import annotations

import functools
import importlib.metadata
import importlib.util
import os
import threading
import time

import mujoco

from vabench import switches
from vabench.sim_mjx.warp.cuda_sync import prefer_blocking_sync
from vabench.sim_mjx.warp.modules import keep_loaded

GPU_EXTRA = "pip install 'vabench[gpu]'"

GPU_SHARE = switches.variable("gpu_share")
"""Environment variable: how many processes share each GPU (set by the processes executor for
its workers). GPU buffers sized from the memory free (the Warp renderer's passes) take
1 / share of it, so that processes sizing at the same moment do not overcommit the card."""


def gpu_share() -> int:
    return int(switches.get("gpu_share"))


def warp_device() -> str:
    """The Warp device the Warp backend uses: VABENCH_WARP_DEVICE, else the first CUDA GPU."""
    return str(switches.get("warp_device"))


class TimedLock:
    """A re-entrant lock that keeps how long its holders waited for it and held it (the
    outermost hold of each thread): the sweep's "host:" lines read them (`lock_figures`), to
    tell a device lock that paces the batches from one that does not."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._local = threading.local()
        self.waited_s = 0.0
        self.held_s = 0.0
        self.acquisitions = 0

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        depth = getattr(self._local, "depth", 0)
        t0 = time.perf_counter()
        if not self._lock.acquire(blocking, timeout):
            return False
        self._local.depth = depth + 1
        if depth == 0:  # counted while held: no other thread writes them now
            now = time.perf_counter()
            self.waited_s += now - t0
            self.acquisitions += 1
            self._local.since = now
        return True

    def release(self) -> None:
        self._local.depth -= 1
        if self._local.depth == 0:
            self.held_s += time.perf_counter() - self._local.since
        self._lock.release()

    def _is_owned(self) -> bool:
        return self._lock._is_owned()  # type: ignore[attr-defined]

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


_DEVICE_LOCKS: dict[str, TimedLock] = {}
_DEVICE_LOCKS_GUARD = threading.Lock()


def lock_figures() -> dict[str, tuple[float, float, int]]:
    """Each device lock of this process: (seconds waited for it, seconds held, holds)."""
    with _DEVICE_LOCKS_GUARD:
        locks = dict(_DEVICE_LOCKS)
    return {name: (lk.waited_s, lk.held_s, lk.acquisitions) for name, lk in locks.items()}


def device_lock(device: str) -> TimedLock:
    """The lock of one Warp device, held by whoever queues work on it (the physics batch for a
    whole action, the renderer for a whole pass). Warp queues every launch of a device on one
    stream, so the work of two threads could interleave: a render that reads a batch's state
    between two substeps of an action would see slots the action has not yet restored."""
    name = str(device)
    with _DEVICE_LOCKS_GUARD:
        made = name not in _DEVICE_LOCKS
        lock = _DEVICE_LOCKS.setdefault(name, TimedLock())
    if made and name.startswith("cuda"):  # outside the guard: the interface imports JAX
        from vabench.sim_mjx.interface import watch_device

        watch_device(name, functools.partial(_failed_context, name))
    return lock


def _failed_context(name: str) -> str | None:
    """Why the CUDA context of device `name` failed (None while it works)."""
    import warp as wp

    from vabench.sim_mjx.warp.streams import context_error

    try:
        device = wp.get_device(name)
    except (RuntimeError, ValueError):  # no such device in this process: nothing of it failed
        return None
    failure = context_error(device)
    return None if failure is None else f"the CUDA context of {name} failed ({failure})"


def nvidia_driver_present(proc: str = "/proc/driver/nvidia") -> bool:
    """An NVIDIA kernel driver is loaded (its /proc directory exists): without one no CUDA
    device can exist, whatever packages are installed."""
    return os.path.isdir(proc)


def warp_problem(device: str | None = None) -> str | None:
    """Why the Warp backend cannot run here (None when it can). Cheap: imports warp only when
    the packages are installed."""
    device = device or warp_device()
    if device.startswith("cuda") and not nvidia_driver_present():
        # the true reason, before any package hint (installing one would give no GPU) and
        # before wp.init (which prints its own warning of the missing driver)
        return (
            "the Warp backend needs an NVIDIA GPU with a CUDA driver; this machine has none "
            "(no NVIDIA driver loaded). Use backend c, or set VABENCH_WARP_DEVICE=cpu to run "
            "Warp on the CPU (slow)"
        )
    for module, package in (("warp", "warp-lang"), ("mujoco_warp", "mujoco-warp")):
        if importlib.util.find_spec(module) is None:
            return f"the Warp backend needs the package {package} ({GPU_EXTRA})"
    prefer_blocking_sync()  # before wp.init makes the GPUs' contexts active
    import warp as wp

    wp.config.quiet = True  # type: ignore[attr-defined]  # not in warp's stubs
    wp.config.log_level = wp.LOG_WARNING  # no 'Module ... load' line per kernel module
    wp.init()
    keep_loaded()
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
