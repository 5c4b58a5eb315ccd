"""How much of a core a thread spends waiting for the GPU, by how it waits: on an event made
by Warp (`wp.Event`, no CU_EVENT_BLOCKING_SYNC), on `streams.sleeping_event` (with it), and on
a stream synchronisation, in a process whose CUDA context asked for blocking sync first
(`cuda_sync.prefer_blocking_sync`, as every engine process does).

    python benchmarks/gpu_waits.py [--wait-s 0.3] [--repeats 5]

Why: CUDA's documentation says a thread waiting on an event made without the flag busy-waits
(whether the context's blocking sync changes that is what this measures: on an H200,
2026-11-29, it did not: Warp's event 1.00, a sleeping event 0.00, a stream sync 1.00); an
engine process waits on an event after every physics action, render pass and JPEG call, and
on an H200 host (2026-11-29) the engine processes' batch and render threads took 0.3-0.9
cores each process while the host's 16 cores were 83 % busy.
Prints, per way of waiting, the waiting thread's CPU seconds per second waited (1.0: a core
spinning; ~0: asleep), side by side in one run.
"""

from __future__ import annotations

import argparse
import sys
import time

import warp as wp

from vabench.sim_mjx.warp import cuda_sync, streams


@wp.kernel
def _busy(n: int, out: wp.array(dtype=float)):  # type: ignore[valid-type]
    """One GPU thread computing for a while (the result is written, so it is not dropped)."""
    x = float(0.0)  # noqa: UP018 - a dynamic variable for the loop (Warp)
    for _ in range(n):
        x = x * 0.999999 + 1.0
    out[0] = x


def _launch(stream: wp.Stream, n: int, out: wp.array) -> None:
    with wp.ScopedStream(stream):
        wp.launch(_busy, dim=1, inputs=[n], outputs=[out])


def measure(
    way: str, stream: wp.Stream, n: int, out: wp.array, repeats: int
) -> tuple[float, float]:
    """(CPU seconds of the waiting thread per second waited, mean seconds waited)."""
    cpu = wall = 0.0
    for _ in range(repeats):
        _launch(stream, n, out)
        if way == "warp event":
            event = stream.record_event()
        elif way == "sleeping event":
            event = streams.record(stream)
        t0, c0 = time.perf_counter(), time.thread_time()
        if way == "stream sync":
            wp.synchronize_stream(stream)
        else:
            streams.wait(event)
        wall += time.perf_counter() - t0
        cpu += time.thread_time() - c0
    return cpu / wall, wall / repeats


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--wait-s", type=float, default=0.3, help="about how long each wait lasts")
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    said = cuda_sync.prefer_blocking_sync()  # before Warp makes its contexts
    wp.init()
    if not wp.is_cuda_available():
        print("no CUDA device: nothing to measure")
        return 1
    device = wp.get_device("cuda:0")
    stream = wp.Stream(device)
    out = wp.zeros(1, dtype=float, device=device)
    n = 1 << 20  # calibrate: one launch of about --wait-s
    _launch(stream, n, out)
    wp.synchronize_stream(stream)
    t0 = time.perf_counter()
    _launch(stream, n, out)
    wp.synchronize_stream(stream)
    n = max(1, int(n * args.wait_s / max(time.perf_counter() - t0, 1e-6)))
    print(f"{device.name}; GPU waits: {said}; each wait ~{args.wait_s:.2f} s, {args.repeats} waits")
    print(f"{'how the thread waits':<20} {'CPU s per s waited':>19} {'mean wait s':>12}")
    for way in ("warp event", "sleeping event", "stream sync"):
        ratio, mean = measure(way, stream, n, out, args.repeats)
        print(f"{way:<20} {ratio:>19.2f} {mean:>12.3f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
