"""How the Warp batch launches its device work: captured CUDA graphs, or plain launches.

The batch hands over callables that only queue Warp launches (no host reads); `Graphs` runs
them as CUDA graphs, each captured on its first use under a name and replayed afterwards, or,
on Warp's CPU device and with graphs off (debugging), launches them directly.
"""

from __future__ import annotations

from collections.abc import Callable

import warp as wp

LOOPS = ("per_step", "unrolled")
"""How graphs hold an action's substeps. per_step (default): a graph of one substep (references,
mujoco_warp.step, counter), launched n times between a graph before and one after; launches
are asynchronous, so nothing returns to the host between substeps. unrolled: one graph for the
whole action. Measured on an H100 (docs/PERFORMANCE.md) both step equally fast, but unrolled
costs 3.5-5 s of capture per batch shape and each distinct hold length. A device-side while
loop (one small graph) is not possible: MuJoCo Warp allocates scratch arrays inside its step,
and CUDA graphs allow no allocation inside a conditional body."""


class Graphs:
    """The graphs of one batch on `device`; `enabled` false launches everything directly.
    Callers hold the device's lock and scope the device around every call."""

    def __init__(self, device: wp.context.Device, enabled: bool, loop: str):
        if loop not in LOOPS:
            raise ValueError(f"loop must be one of {LOOPS}, got {loop!r}")
        self.device = device
        self.enabled = enabled
        self.loop = loop
        self._graphs: dict[str, wp.Graph] = {}

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
    ) -> None:
        """pre, n x substep, post: as graphs (see LOOPS) or as plain launches."""
        if not self.enabled:
            pre()
            for _ in range(n):
                substep()
            post()
        elif self.loop == "per_step":
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

    def clear(self) -> None:
        self._graphs.clear()
