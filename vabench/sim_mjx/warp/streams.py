"""How a thread queues work on the GPU and then waits for it without holding up the others.

Warp keeps one current stream per device for the whole process, not per thread, so whoever
queues device work holds the device's lock (`device.device_lock`) with its own stream current
(`queueing`). What it then waits for is the GPU, and it waits with the lock released: each
physics batch and each render pass has a CUDA stream of its own, queues its work there under
the lock (a batch action is a few tens of ms of host time, less than its GPU time), records an
event (one its waiters sleep on: `sleeping_event`), lets go of the lock and sleeps on the
event (`wait`). The GPU then runs the batches' actions and the renderer's passes side by side,
on their streams, while the host queues the next ones. Before this, every action held the
lock until its results were on the host, so the GPU ran one batch at a time and the threads of
the other batches queued behind the lock (docs/PERFORMANCE.md, "Engine processes on one GPU").

Results reach the host through `Readback`: device arrays mirrored into pinned host buffers by
copies queued behind the work, so that the host reads them once the event has passed, with no
synchronous copy under the lock.

On Warp's CPU device there are no streams or events: work runs when it is queued, and every
function here degrades to that.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
from collections.abc import Iterator
from typing import Any

import numpy as np
import warp as wp

from vabench.sim_mjx.interface import device_failure
from vabench.sim_mjx.warp import cuda_sync

log = logging.getLogger(__name__)


@contextlib.contextmanager
def queueing(
    lock: contextlib.AbstractContextManager[Any],
    device: wp.context.Device,
    stream: wp.Stream | None,
) -> Iterator[None]:
    """Hold `lock` with `device` current and `stream` its current stream (CUDA). The stream
    does not wait for the one it replaces (`sync_enter=False`): batches and passes are
    independent, and a false dependency would serialise them again. An error inside that
    comes from a failed CUDA context is raised as `DeviceFailure` (`failing_device`)."""
    with lock, wp.ScopedDevice(device), failing_device():
        if stream is None:
            yield
        else:
            with wp.ScopedStream(stream, sync_enter=False):
                yield


@contextlib.contextmanager
def failing_device() -> Iterator[None]:
    """Raise an error inside as `DeviceFailure` when a CUDA context of this process has failed.

    After a sticky CUDA error (an illegal memory access in any kernel of the process) every
    later call on the device fails: allocations ('Failed to allocate 4 bytes'), module loads,
    nvImageCodec. Recorded as each episode's harness error, one such error would end every
    episode of a sweep within seconds, none re-run by a resume. The
    check (`interface.device_failure`: the context checks `device.device_lock` registered for
    each device queued on) runs only once something has already failed."""
    try:
        yield
    except Exception as err:
        failure = device_failure(err)
        if failure is not None and failure is not err:
            raise failure from err
        raise


STICKY_ERRORS = {
    214: "CUDA_ERROR_ECC_UNCORRECTABLE",
    700: "CUDA_ERROR_ILLEGAL_ADDRESS",
    702: "CUDA_ERROR_LAUNCH_TIMEOUT",
    709: "CUDA_ERROR_CONTEXT_IS_DESTROYED",
    710: "CUDA_ERROR_ASSERT",
    714: "CUDA_ERROR_HARDWARE_STACK_ERROR",
    715: "CUDA_ERROR_ILLEGAL_INSTRUCTION",
    716: "CUDA_ERROR_MISALIGNED_ADDRESS",
    717: "CUDA_ERROR_INVALID_ADDRESS_SPACE",
    718: "CUDA_ERROR_INVALID_PC",
    719: "CUDA_ERROR_LAUNCH_FAILED",
    805: "CUDA_ERROR_MPS_CONNECTION_FAILED",
    806: "CUDA_ERROR_MPS_RPC_FAILURE",
    807: "CUDA_ERROR_MPS_SERVER_NOT_READY",
    810: "CUDA_ERROR_MPS_CLIENT_TERMINATED",
}
"""The driver's errors after which a context can do nothing more (a kernel's fault, a dead
MPS server). Others a synchronisation may report (one about another thread's graph capture,
say) say nothing about the context's health."""


def context_error(device: wp.context.Device) -> str | None:
    """The sticky error the CUDA context of `device` reports when synchronised (after a kernel
    fault: `STICKY_ERRORS`), or None when it works (and on the CPU). Waits for the device's
    queued work: for error paths only."""
    if not device.is_cuda:
        return None
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return None
    if cuda.cuCtxPushCurrent_v2(ctypes.c_void_p(device.context)) != 0:
        return "the context cannot be made current"
    try:
        code = cuda.cuCtxSynchronize()
    finally:
        cuda.cuCtxPopCurrent_v2(ctypes.byref(ctypes.c_void_p()))
    if code not in STICKY_ERRORS:
        return None
    name = ctypes.c_char_p()
    cuda.cuGetErrorName(code, ctypes.byref(name))
    return f"CUDA error {code}: {(name.value or b'?').decode()}"


CU_STREAM_NON_BLOCKING = 0x1


PRIORITIES = ("least", "middle", "greatest")
"""The stream priorities the engine uses, within the device's range (`priority_value`):

- least: the render passes' ray tracing. Its megakernel (one thread a pixel, ~50 ms a pass of
  ~60 worlds at 1280x960) is most of the engine processes' GPU kernel time
  (docs/PERFORMANCE.md, "Whole suite on one GPU"), and a kernel of another stream waits
  behind its pending blocks;
- middle: the physics batches' actions and the JPEG encodes, chains of small kernels whose
  every link waited behind those blocks (a JPEG call took about a hundred times its kernels'
  time);
- greatest: the sweep's critical path (`WarpBatch.critical_path`), physics and images alike.

The GPU dispatches pending blocks of a higher-priority stream first (never preempting running
ones), so a small kernel slips in beside a megakernel instead of after it; the total work is
the same."""


def priority_value(level: str, least: int, greatest: int) -> int:
    """CUDA's priority number for `level` (one of `PRIORITIES`) on a device whose range is
    `least` (CUDA's default, 0) to `greatest` (a smaller number, e.g. -5): middle halfway,
    rounded towards greatest (a range of two levels has no middle: greatest)."""
    if level not in PRIORITIES:
        raise ValueError(f"stream priority must be one of {PRIORITIES}, got {level!r}")
    if level == "least":
        return least
    if level == "greatest":
        return greatest
    return least - (least - greatest + 1) // 2


def new_stream(device: wp.context.Device, priority: str = "least") -> wp.Stream | None:
    """A non-blocking stream of its own on a CUDA device (None on the CPU), at `priority`
    (`PRIORITIES`).

    Non-blocking: work on CUDA's legacy default stream does not wait for it, nor it for that
    work. Warp makes blocking streams, and with them nvImageCodec's encodes (which synchronise
    through the legacy stream) broke the graph capture of any batch capturing at that moment
    ("operation would make the legacy stream depend on a capturing blocking stream", then
    CUDA error 901 in every launch of that capture, hundreds of episodes lost to harness
    errors). Made through the driver API and handed to Warp as an external stream;
    where the driver refuses, a blocking Warp stream (logged)."""
    if priority not in PRIORITIES:  # on every device, the CPU's too
        raise ValueError(f"stream priority must be one of {PRIORITIES}, got {priority!r}")
    if not device.is_cuda:
        return None
    handle = _nonblocking_stream(device.context, priority)
    if handle is None:
        log.warning("streams: the CUDA driver made no non-blocking stream; using a blocking one")
        return wp.Stream(device)
    return wp.Stream(device, cuda_stream=handle)


def _nonblocking_stream(context: Any, priority: str = "least") -> int | None:
    """cuStreamCreateWithPriority(CU_STREAM_NON_BLOCKING) in `context` (Warp's primary context
    of the device), at `priority` within the context's range (`priority_value`); never
    destroyed: a process makes a few dozen (one per batch, render pass and encoding thread)."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return None
    if cuda.cuCtxPushCurrent_v2(ctypes.c_void_p(context)) != 0:
        return None
    try:
        value = 0  # CUDA's default; lower numbers are higher priorities
        least, greatest = ctypes.c_int(), ctypes.c_int()
        if cuda.cuCtxGetStreamPriorityRange(ctypes.byref(least), ctypes.byref(greatest)) == 0:
            value = priority_value(priority, least.value, greatest.value)
        stream = ctypes.c_void_p()
        flags = ctypes.c_uint(CU_STREAM_NON_BLOCKING)
        if cuda.cuStreamCreateWithPriority(ctypes.byref(stream), flags, value) != 0:
            return None
        return stream.value
    finally:
        cuda.cuCtxPopCurrent_v2(ctypes.byref(ctypes.c_void_p()))


def record(stream: wp.Stream | None) -> wp.Event | None:
    """An event at the end of the work queued so far on `stream` (None on the CPU), made so that
    a thread waiting on it sleeps (`sleeping_event`)."""
    if stream is None:
        return None
    return stream.record_event(sleeping_event(stream.device))


BLOCKING_SYNC = 0x1  # CU_EVENT_BLOCKING_SYNC (Warp's Event.Flags use CUDA's values)
DISABLE_TIMING = 0x2  # CU_EVENT_DISABLE_TIMING


def sleeping_event(device: Any) -> wp.Event:
    """A CUDA event whose waiters sleep until it passes (CU_EVENT_BLOCKING_SYNC), without
    timing: CUDA's documentation of cuEventSynchronize says a thread waiting on an event made
    without that flag busy-waits, and `wp.Event` offers no way to ask for it. Each engine
    process's batch and render threads wait on one after every action and pass. Measured
    (`benchmarks/gpu_waits.py`, in a process whose context asked for blocking sync): a waiter
    on Warp's event spins a core for its whole wait, on this one it sleeps, and the suite's
    host gets cores back (docs/PERFORMANCE.md, "Engine processes on one GPU"). With
    `VABENCH_CUDA_SYNC=spin`, or where Warp's call is missing,
    Warp's own event."""
    from warp._src import context  # Warp's event call with flags; public API otherwise

    core: Any = getattr(context.runtime, "core", None)
    if not cuda_sync.blocking_events() or not hasattr(core, "wp_cuda_event_create"):
        return wp.Event(device)
    handle = core.wp_cuda_event_create(device.context, BLOCKING_SYNC | DISABLE_TIMING)
    if not handle:
        return wp.Event(device)
    event = wp.Event(device, cuda_event=handle)
    event.owner = True  # destroyed with the object, as Warp's own
    return event


def wait(event: wp.Event | None) -> None:
    """Block this thread (without the GIL, asleep: `sleeping_event`) until `event` has passed.

    `wp.synchronize_event` refuses while any graph capture is open on the device, another
    thread's included; Warp captures in CUDA's thread-local mode, in which other threads may
    wait on events, so this calls the same runtime function without that check."""
    if event is None:
        return
    from warp._src import context  # the check-free call; public API otherwise

    runtime: Any = context.runtime
    core = getattr(runtime, "core", None)
    if core is None or not hasattr(core, "wp_cuda_event_synchronize"):
        wp.synchronize_event(event)
        return
    if not core.wp_cuda_event_synchronize(event.cuda_event):
        with failing_device():
            raise RuntimeError(
                f"CUDA reported an error waiting for the GPU: {runtime.get_error_string()}"
            )


class Readback:
    """Named device arrays copied to host buffers behind the work that fills them.

    `queue()` (under `queueing`) adds the copies to the current stream: into pinned host
    memory on a GPU (asynchronous), into plain host arrays on Warp's CPU device (done at once).
    Once the caller has waited for an event recorded after them, `values()` returns copies of
    the host buffers, read through NumPy's array interface: host memory, no device work, so
    no lock."""

    def __init__(self, device: wp.context.Device):
        self.device = device
        self._pairs: dict[str, tuple[wp.array, wp.array]] = {}

    def add(self, name: str, array: wp.array) -> None:
        """Mirror `array` (call under `queueing`: the host buffer is allocated here)."""
        pinned = self.device.is_cuda
        host = wp.empty(array.shape, dtype=array.dtype, device="cpu", pinned=pinned)
        self._pairs[name] = (array, host)

    def __contains__(self, name: str) -> bool:
        return name in self._pairs

    def queue(self) -> None:
        for array, host in self._pairs.values():
            wp.copy(host, array)

    def values(self) -> dict[str, np.ndarray]:
        return {name: np.array(host) for name, (_, host) in self._pairs.items()}
