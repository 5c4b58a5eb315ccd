"""How a host thread waits for this process's GPU work: blocking, not spinning.

CUDA's default scheduling (`CU_CTX_SCHED_AUTO`) makes a thread that waits for the GPU (a
stream synchronisation, a device-to-host copy, nvImageCodec returning its bytes) spin on its
core whenever the process has fewer CUDA contexts than the host has cores, which is always the
case here. One process waiting that way costs one core; sixteen cell workers sharing one GPU,
each waiting its turn, would spin sixteen cores while the model side (the embedded server's
policy, JPEG decoding, the engine's JSON) needs them. `prefer_blocking_sync` asks the driver to
put waiting threads to sleep instead (`CU_CTX_SCHED_BLOCKING_SYNC` on every GPU's primary
context, the context Warp uses), which costs a few microseconds of wake-up per wait: nothing
next to an action's ~90 ms of physics. Measured (`benchmarks/gpu_waits.py`; docs/PERFORMANCE.md,
"Engine processes on one GPU"), the flag set and confirmed by the driver did not make a stream
synchronisation or a wait on Warp's events sleep (1.00 CPU second per second waited each):
what sleeps is an event made with its own flag (`blocking_events`, `streams.sleeping_event`,
0.00), on which every wait of the engine's hot paths now is. The context flag stays: harmless,
and the driver's other waits may honour it.

It must run before the process's primary contexts become active (Warp initialises them in
`wp.init`), so `backends.warp_problem`, the first Warp call on every path, makes it. Where the
driver refuses (a context already active), the log says so and CUDA's default stays.
`VABENCH_CUDA_SYNC=spin` keeps the default on purpose (to compare the two).
"""

from __future__ import annotations

import ctypes
import logging

from vabench import switches

log = logging.getLogger(__name__)

SYNC_VARIABLE = switches.variable("cuda_sync")
MODES = ("block", "spin")
CU_CTX_SCHED_BLOCKING_SYNC = 0x04

_done: str | None = None


def blocking_events() -> bool:
    """Whether events the host waits on are made to sleep (`streams.record`): CUDA's
    documentation of cuEventSynchronize says a thread waiting on an event created without
    CU_EVENT_BLOCKING_SYNC busy-waits, and Warp's events are created without it. The context's
    blocking sync above does not cover them, nor, measured, a stream synchronisation
    (`benchmarks/gpu_waits.py`, the driver confirming the context's flag): a waiter on Warp's
    event and one in `wp.synchronize_stream` each used 1.00 CPU second per
    second waited, one on a sleeping event 0.00. So every wait of the engine's hot paths is on
    a sleeping event. Off with VABENCH_CUDA_SYNC=spin too."""
    return switches.get("cuda_sync") != "spin"


def prefer_blocking_sync() -> str:
    """Make waits on this process's GPUs block (once per process); returns what was done, in
    words. Raises ValueError for a VABENCH_CUDA_SYNC that is neither block nor spin."""
    global _done
    if _done is None:
        _done = _set_flags(switches.get("cuda_sync"))
        log.info("GPU waits: %s", _done)
    return _done


def _set_flags(mode: str) -> str:
    if mode not in MODES:
        raise ValueError(f"{SYNC_VARIABLE} must be one of {MODES}, got {mode!r}")
    if mode == "spin":
        return f"CUDA's default scheduling ({SYNC_VARIABLE}=spin)"
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return "no CUDA driver here"
    if cuda.cuInit(0) != 0:
        return "CUDA's default scheduling (cuInit failed)"
    count = ctypes.c_int(0)
    if cuda.cuDeviceGetCount(ctypes.byref(count)) != 0 or count.value == 0:
        return "no CUDA device here"
    set_flags = getattr(cuda, "cuDevicePrimaryCtxSetFlags_v2", None)
    if set_flags is None:
        set_flags = cuda.cuDevicePrimaryCtxSetFlags
    refused = []
    for ordinal in range(count.value):
        device = ctypes.c_int(0)
        result = cuda.cuDeviceGet(ctypes.byref(device), ordinal)
        if result == 0:
            result = set_flags(device, CU_CTX_SCHED_BLOCKING_SYNC)
        if result != 0:
            refused.append(f"GPU {ordinal}: CUresult {result}")
    if refused:
        return "CUDA's default scheduling where the driver refused (" + "; ".join(refused) + ")"
    return f"blocking sync on {count.value} GPU(s) (threads sleep while the GPU works)"
