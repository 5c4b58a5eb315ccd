"""The inclusive scan in Warp kernels (`vabench.render.warp_scan`) on Warp's CPU device, the
kernels a GPU runs, against numpy's cumsum: one level and several, at and around the chunk's
edges, in place, both integer types; bad calls refused. Why it exists (Warp's own scan frees
its scratch memory unordered with our non-blocking streams) is a GPU's matter, checked by
benchmarks/jpeg_contention.py `--encoder warp` on the device; here: that warp_jpeg no longer
calls anything of Warp's that allocates per call."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("warp", reason="warp_scan needs warp-lang (the [test] extra has it)")

import warp as wp

from vabench.render import warp_jpeg, warp_scan

C = warp_scan.CHUNK


@pytest.mark.parametrize("dtype, np_dtype", [(wp.int32, np.int32), (wp.int64, np.int64)])
def test_it_is_numpy_s_cumsum(dtype, np_dtype):
    rng = np.random.default_rng(1)
    capacity = C**3 + 5  # four levels
    scan = warp_scan.InclusiveScan(dtype, capacity, "cpu")
    for m in (1, 2, C - 1, C, C + 1, C * C - 1, C * C, C * C + 1, 3 * C * C + 17, capacity):
        values = rng.integers(-1000, 1000, m).astype(np_dtype)
        src = wp.array(values, dtype=dtype, device="cpu")
        out = wp.full(m + 3, 7, dtype=dtype, device="cpu")  # longer than m: the rest untouched
        scan(src, out, m)
        np.testing.assert_array_equal(out.numpy()[:m], np.cumsum(values), err_msg=f"m={m}")
        np.testing.assert_array_equal(out.numpy()[m:], 7)
        np.testing.assert_array_equal(src.numpy(), values)  # the input is left as it was


def test_in_place_and_large_int64_sums():
    """In place (out is values), and sums past 2**31 (bit offsets of many frames)."""
    values = np.full(5 * C * C, 3_000_000, np.int64)
    arr = wp.array(values, dtype=wp.int64, device="cpu")
    warp_scan.InclusiveScan(wp.int64, len(values), "cpu")(arr, arr, len(values))
    assert arr.numpy()[-1] == 3_000_000 * len(values) > 2**31
    np.testing.assert_array_equal(arr.numpy(), np.cumsum(values))


def test_bad_calls_are_refused():
    scan = warp_scan.InclusiveScan(wp.int32, 100, "cpu")
    ints = wp.zeros(200, dtype=wp.int32, device="cpu")
    with pytest.raises(ValueError, match="101 values for a capacity of 100"):
        scan(ints, ints, 101)
    with pytest.raises(ValueError, match="0 values"):
        scan(ints, ints, 0)
    longs = wp.zeros(50, dtype=wp.int64, device="cpu")
    with pytest.raises(ValueError, match="arrays of"):
        scan(longs, longs, 10)
    with pytest.raises(ValueError, match="is not int32 or int64"):
        warp_scan.InclusiveScan(wp.float32, 10, "cpu")


def test_warp_jpeg_allocates_nothing_per_call(monkeypatch):
    """Warp's array_scan and radix_sort allocate scratch per call and free it on the legacy
    stream: on a GPU that raced with the encoder's non-blocking stream (CUDA error 700 in the
    main job, 2026-11-28). After its first call an encoder allocates no array at all."""
    from warp._src import types as warp_types

    from vabench.render.images import ImageSettings

    frames = wp.array(
        np.random.default_rng(2).integers(0, 1 << 24, (3, 40 * 56)).astype(np.uint32),
        dtype=wp.uint32,
        device="cpu",
    )
    settings = ImageSettings(56, 40, 90, "420")
    encoder = warp_jpeg.WarpJpeg(3, 56, 40, "cpu")
    encoder.encode(frames, 3, settings)
    made: list[tuple] = []
    new = warp_types.array._init_new

    def counted(self, *args, **kwargs):
        made.append(args[:2])
        return new(self, *args, **kwargs)

    monkeypatch.setattr(warp_types.array, "_init_new", counted)
    encoder.encode(frames, 3, settings)
    encoder.encode(frames, 2, settings)
    assert made == []
    encoder.encode(frames, 3, ImageSettings(56, 40, 90, "444"))  # more blocks: buffers grow
    assert made, "nothing counted: the check above could not fail"


def test_a_partly_overlapping_output_is_refused():
    scan = warp_scan.InclusiveScan(wp.int32, 100, "cpu")
    ints = wp.zeros(200, dtype=wp.int32, device="cpu")
    with pytest.raises(ValueError, match="overlaps"):
        scan(ints, ints[1:], 50)
    scan(ints, ints[100:], 50)  # apart: fine
