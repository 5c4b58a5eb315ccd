"""An inclusive prefix sum in Warp kernels, queued on the caller's stream, with its scratch
memory allocated once: `warp_jpeg`'s scans of block bit lengths and of stuffed bytes.

Why not `wp.utils.array_scan` (Warp 1.19): its CUB scan allocates scratch memory on the
current stream and frees it at once with `cudaFreeAsync(ptr, 0)`, ordered on the legacy
stream, on the assumption that the legacy stream waits for the others. A stream made with
`cudaStreamNonBlocking` (ours: `streams.new_stream`) is not waited for, so the scratch goes back
to the memory pool while the scan may still be running, and another thread's scan on its own
stream can be handed the same block: four encoders in four threads (benchmarks/
jpeg_contention.py `--encoder warp`) stopped with CUDA error 700 (an illegal address) and
corrupt JPEGs where one encoder alone was right. Here nothing is allocated or freed per call.

How: values in chunks of `CHUNK`, a thread a chunk. A level sums each chunk (`_totals`), the
chunk totals are scanned the same way one level up (in place), and each chunk is then scanned
from the total of the chunks before it (`_scan`); a level of at most `CHUNK` values is one
thread's loop. 2.5 million values (128 frames of 1280x960 in 8x8 blocks) take four levels and
seven launches.
"""

# Warp kernels: a variable a dynamic loop changes is declared with its type.
from __future__ import annotations

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "max_unroll": 1})

CHUNK = 64
"""Values one thread adds in a level."""


def _kernels(dtype: Any) -> tuple[Any, Any]:
    """The two kernels of a level for values of `dtype` (wp.int32 or wp.int64)."""

    @wp.kernel
    def totals(values: wp.array(dtype=dtype), m: int, out: wp.array(dtype=dtype)):
        t = wp.tid()
        total = dtype(0)
        for j in range(t * CHUNK, wp.min(t * CHUNK + CHUNK, m)):  # type: ignore[arg-type]
            total += values[j]
        out[t] = total

    @wp.kernel
    def scan(
        values: wp.array(dtype=dtype),
        m: int,
        before: wp.array(dtype=dtype),
        offset: int,
        out: wp.array(dtype=dtype),
    ):
        """out[j] = the sum of values[:j + 1] within the chunk, plus before[t - 1] (the chunks
        before it) where `offset` is 1. In place (out is values) is fine: a thread reads each
        value before writing it."""
        t = wp.tid()
        running = dtype(0)
        if offset == 1 and t > 0:
            running = before[t - 1]
        for j in range(t * CHUNK, wp.min(t * CHUNK + CHUNK, m)):  # type: ignore[arg-type]
            running += values[j]
            out[j] = running

    return totals, scan


_KERNELS = {wp.int32: _kernels(wp.int32), wp.int64: _kernels(wp.int64)}


def _chunks(m: int) -> int:
    return -(-m // CHUNK)


class InclusiveScan:
    """Inclusive prefix sums of up to `capacity` values of `dtype` on `device`. Make it and
    call it with the stream it runs on current (its scratch is allocated on that stream);
    calls on one instance must be ordered (one stream, or the caller's lock and events)."""

    def __init__(self, dtype: Any, capacity: int, device: Any):
        if dtype not in _KERNELS:
            raise ValueError(f"InclusiveScan: dtype {dtype} is not int32 or int64")
        self.dtype, self.capacity, self.device = dtype, capacity, wp.get_device(device)
        self._levels: list[wp.array] = []
        m = capacity
        while m > CHUNK:
            m = _chunks(m)
            self._levels.append(wp.empty(m, dtype=dtype, device=self.device))
        self._none = wp.zeros(1, dtype=dtype, device=self.device)

    def __call__(self, values: wp.array, out: wp.array, m: int) -> None:
        """Queue out[:m] = cumsum(values[:m]) on the current stream (`out` may be `values`)."""
        if not 0 < m <= min(self.capacity, values.shape[0], out.shape[0]):
            raise ValueError(
                f"InclusiveScan: {m} values for a capacity of {self.capacity} "
                f"({values.shape[0]} in, {out.shape[0]} out)"
            )
        same, apart = (
            out.ptr == values.ptr,
            (
                out.ptr + m * out.strides[0] <= values.ptr
                or values.ptr + m * values.strides[0] <= out.ptr
            ),
        )
        if not (same or apart):
            raise ValueError("InclusiveScan: `out` overlaps `values` without being it")
        if values.dtype != self.dtype or out.dtype != self.dtype:
            raise ValueError(
                f"InclusiveScan of {self.dtype}: arrays of {values.dtype} and {out.dtype}"
            )
        self._level(values, out, m, 0)

    def _level(self, values: wp.array, out: wp.array, m: int, level: int) -> None:
        totals, scan = _KERNELS[self.dtype]
        d = self.device
        if m <= CHUNK:
            wp.launch(scan, dim=1, inputs=[values, m, self._none, 0, out], device=d)
            return
        k, sums = _chunks(m), self._levels[level]
        wp.launch(totals, dim=k, inputs=[values, m, sums], device=d)
        self._level(sums, sums, k, level + 1)
        wp.launch(scan, dim=k, inputs=[values, m, sums, 1, out], device=d)
