"""How the Warp batch launches its device work: captured CUDA graphs, or plain launches.

The batch hands over callables that only queue Warp launches (no host reads); `Graphs` runs
them as CUDA graphs, each captured on its first use under a name and replayed afterwards, or,
on Warp's CPU device and with graphs off (debugging), launches them directly.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator

import warp as wp

log = logging.getLogger(__name__)

LOOPS = ("device", "per_step", "unrolled")
"""How graphs hold an action's substeps.

device (default on a GPU): one graph per action whose substeps run in a CUDA while-loop node
(`wp.capture_while`): the host queues one graph launch per action, whatever its substeps.
per_step: a graph of one substep launched n times between a graph before and one after;
nothing returns to the host between substeps, but the host queues n graph launches, and the
cost of a launch grows with its nodes: tens of ms of host time per 200-substep action
(docs/PERFORMANCE.md, "Engine processes on one GPU"), during which the device's lock is held
and no other batch
can queue. unrolled: one graph holding every substep (3.5-5 s of capture per batch shape and
each distinct hold length, and no faster to launch).

A while-loop body may hold no memory-allocation node, and MuJoCo Warp allocates scratch
arrays inside its step: while a device loop is captured, the device's allocator is an
`Arena`, which hands out slices of one block allocated before the capture (never reused,
freed with the graph), so the graph holds kernels and copies only. Where the driver or the
body refuses the loop, the batch falls back to per_step for good (logged once)."""

CAPTURE_FAILED = "device loop refused"

Condition = Callable[[wp.array], None]


class Arena:
    """A Warp allocator that slices one device block: the scratch arrays a captured graph
    keeps using at every replay. Frees are no-ops (the graph owns the memory until the arena
    is dropped); running out raises `MemoryError` (the caller retries with a larger arena)."""

    ALIGN = 256
    deallocate_requires_context_guard = False

    def __init__(self, device: wp.context.Device, size: int):
        self.device = device
        self.size = size
        self.block = wp.empty(size, dtype=wp.uint8, device=device)  # before the capture
        self.used = 0

    def allocate(self, size_in_bytes: int) -> int:
        start = -(-self.used // self.ALIGN) * self.ALIGN
        if start + size_in_bytes > self.size:
            raise MemoryError(f"arena of {self.size} bytes exhausted")
        self.used = start + size_in_bytes
        return int(self.block.ptr) + start

    def deallocate(self, ptr: int, size_in_bytes: int) -> None:
        pass


@contextlib.contextmanager
def allocating_from(device: wp.context.Device, arena: Arena) -> Iterator[None]:
    """Make `arena` the device's allocator (the caller holds the device's lock)."""
    saved = getattr(device, "_custom_allocator", None)  # None: Warp's built-in allocator
    wp.set_device_allocator(device, arena)
    try:
        yield
    finally:
        wp.set_device_allocator(device, saved)


@wp.kernel
def _loop_condition(k: wp.array(dtype=int), n: int, go_on: wp.array(dtype=wp.int32)):
    """The while node's condition: substeps done (k[0]) below n."""
    go_on[0] = wp.where(k[0] < n, 1, 0)


ARENA_BYTES = 16 << 20  # first arena of a device-loop capture; x4 per retry
ARENA_LIMIT = 1 << 30


class Graphs:
    """The graphs of one batch on `device`; `enabled` false launches everything directly.
    Callers hold the device's lock and scope the device (and the batch's stream) around every
    call."""

    def __init__(self, device: wp.context.Device, enabled: bool, loop: str):
        if loop not in LOOPS:
            raise ValueError(f"loop must be one of {LOOPS}, got {loop!r}")
        self.device = device
        self.enabled = enabled
        self.loop = loop
        self._graphs: dict[str, wp.Graph] = {}
        self._arenas: dict[str, Arena] = {}
        self._go_on: wp.array | None = None

    def run(self, name: str, body: Callable[[], None]) -> None:
        """Launch `body` as the CUDA graph `name`, captured on first use (or directly)."""
        if not self.enabled:
            body()
            return
        graph = self._graphs.get(name)
        if graph is None:
            with wp.ScopedCapture(device=self.device) as capture:
                body()
            graph = self._graphs[name] = capture.graph
        wp.capture_launch(graph)

    def run_loop(
        self,
        name: str,
        pre: Callable[[], None],
        substep: Callable[[], None],
        post: Callable[[], None],
        n: int,
        counter: wp.array | None = None,
        condition: Condition | None = None,
    ) -> None:
        """pre, n x substep, post: as graphs (see LOOPS) or as plain launches. `counter`: the
        device's count of substeps done, zeroed by `pre`, incremented by `substep` (the
        device loop's condition reads it). `condition(go_on)`: queues a kernel writing 1 to
        go_on[0] while the loop goes on (default: below n substeps); the loop may end early
        only where it runs on the device (the device loop) or on the CPU device, else it runs
        n substeps, so `substep` must make the extra ones change no result."""
        if not self.enabled:
            pre()
            go_on = wp.zeros(1, dtype=wp.int32) if condition is not None else None
            for _ in range(n):
                substep()
                if condition is not None and go_on is not None:
                    condition(go_on)
                    if not int(go_on.numpy()[0]):
                        break
            post()
            return
        if self.loop == "device" and counter is not None:
            graph = self._device_loop(name, pre, substep, post, n, counter, condition)
            if graph is not None:
                wp.capture_launch(graph)
                return
        if self.loop in ("per_step", "device"):
            self.run(f"{name}.pre", pre)
            for _ in range(n):
                self.run(f"{name}.step", substep)
            self.run(f"{name}.post", post)
        else:

            def body() -> None:
                pre()
                for _ in range(n):
                    substep()
                post()

            self.run(f"{name}.{n}", body)

    def _device_loop(self, name, pre, substep, post, n, counter, condition) -> wp.Graph | None:
        """The graph of pre, a while node of `substep` until `counter` reaches n, post:
        captured on first use with an arena for MuJoCo Warp's scratch arrays (None, and
        per_step from then on, where CUDA refuses the loop)."""
        key = f"{name}.loop{n}"
        graph = self._graphs.get(key)
        if graph is not None:
            return graph
        if self._go_on is None:
            self._go_on = wp.zeros(1, dtype=wp.int32)
        go_on = self._go_on

        def test() -> None:
            if condition is None:
                wp.launch(_loop_condition, dim=1, inputs=[counter, n, go_on])
            else:
                condition(go_on)

        def body() -> None:
            pre()
            test()

            def one() -> None:
                substep()
                test()

            wp.capture_while(go_on, one)
            post()

        size = ARENA_BYTES
        while True:
            arena = Arena(self.device, size)
            try:
                with (
                    allocating_from(self.device, arena),
                    wp.ScopedCapture(device=self.device) as capture,
                ):
                    body()
            except MemoryError:
                if size >= ARENA_LIMIT:
                    self._refuse(f"its scratch arrays exceed {ARENA_LIMIT >> 20} MiB")
                    return None
                size *= 4
                continue
            except RuntimeError as err:  # no conditional nodes here, or a body CUDA refuses
                self._refuse(str(err))
                return None
            self._arenas[key] = arena
            self._graphs[key] = capture.graph
            return capture.graph

    def _refuse(self, why: str) -> None:
        log.warning("%s (%s): stepping with a graph per substep (per_step)", CAPTURE_FAILED, why)
        self.loop = "per_step"
        return None

    def clear(self) -> None:
        self._graphs.clear()
        self._arenas.clear()
