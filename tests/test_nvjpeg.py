"""vabench.render.nvjpeg's calls into nvJPEG, against a stand-in library (no GPU here).

What stands in: libnvjpeg and libcuda's functions, recording each call and writing what the real
ones write through their pointers. What is tested: the order of the calls (every image queued on
the caller's stream, the stream waited for once, then each image's bytes retrieved: length, then
data), the encoder states and parameters reused from call to call, the frame's row pitch and
pointer passed through, and every failure turned into an error naming the call.
"""

from __future__ import annotations

import ctypes

import pytest

from vabench.render import nvjpeg
from vabench.render.images import ImageSettings

JPEG = b"\xff\xd8" + b"payload" + b"\xff\xd9"


class Frame:
    def __init__(self, pointer: int, height=4, width=6, strides=None, typestr="|u1"):
        self.__cuda_array_interface__ = {
            "shape": (height, width, 3),
            "typestr": typestr,
            "data": (pointer, False),
            "strides": strides,
            "version": 2,
        }


class Frames:
    def __init__(self, frames):
        self.frames = frames
        self.shape = (len(frames), 4, 6, 3)

    def __getitem__(self, i):
        return self.frames[i]


class StandIn:
    """libnvjpeg and libcuda: each function records (name, arguments) and returns a status."""

    def __init__(self, jpeg=JPEG):
        self.calls: list[tuple] = []
        self.fail: str | None = None
        self.jpeg = jpeg
        self._next = 100
        self.encoded: dict[int, tuple] = {}

    def _handle(self, out) -> None:
        self._next += 1
        out._obj.value = self._next

    def _status(self, name: str) -> int:
        return 7 if self.fail == name else 0

    def nvjpegCreateSimple(self, out):
        self.calls.append(("create",))
        self._handle(out)
        return self._status("nvjpegCreateSimple")

    def nvjpegEncoderStateCreate(self, handle, out, stream):
        self.calls.append(("state", stream))
        self._handle(out)
        return self._status("nvjpegEncoderStateCreate")

    def nvjpegEncoderParamsCreate(self, handle, out, stream):
        self.calls.append(("params", stream))
        self._handle(out)
        return 0

    def nvjpegEncoderParamsSetQuality(self, params, quality, stream):
        self.calls.append(("quality", quality))
        return 0

    def nvjpegEncoderParamsSetSamplingFactors(self, params, css, stream):
        self.calls.append(("sampling", css))
        return 0

    def nvjpegEncodeImage(self, handle, state, params, image, fmt, width, height, stream):
        img = image._obj
        self.calls.append(("encode", state.value, fmt, width, height, stream))
        self.encoded[state.value] = (img.channel[0], img.pitch[0])
        return self._status("nvjpegEncodeImage")

    def nvjpegEncoderStateDestroy(self, state):
        self.calls.append(("destroy state", state.value))
        return 0

    def nvjpegEncoderParamsDestroy(self, params):
        self.calls.append(("destroy params", params.value))
        return 0

    def nvjpegDestroy(self, handle):
        self.calls.append(("destroy", handle.value))
        return 0

    def cuStreamSynchronize(self, stream):
        self.calls.append(("sync", stream))
        return 0

    def nvjpegEncodeRetrieveBitstream(self, handle, state, data, length, stream):
        size = length._obj
        if data is None:
            self.calls.append(("length", state.value))
            size.value = len(self.jpeg)
        else:
            self.calls.append(("data", state.value))
            ctypes.memmove(data, self.jpeg, len(self.jpeg))
        return self._status("nvjpegEncodeRetrieveBitstream")


@pytest.fixture
def lib(monkeypatch):
    fake = StandIn()
    monkeypatch.setattr(nvjpeg, "load", lambda: (fake, fake))
    return fake


def test_every_image_is_queued_then_waited_for_once_then_retrieved(lib):
    enc = nvjpeg.NvJpeg(0)
    frames = Frames([Frame(0x1000), Frame(0x2000, strides=(32, 3, 1))])
    out = enc.encode(frames, ImageSettings(width=6, height=4, quality=90), cuda_stream=55)
    assert out == [JPEG, JPEG]
    kinds = [c[0] for c in lib.calls]
    assert kinds == [
        "create", "params", "quality", "sampling", "state", "state",
        "encode", "encode", "sync", "length", "data", "length", "data",
    ]  # fmt: skip
    assert ("quality", 90) in lib.calls and ("sampling", nvjpeg.SUBSAMPLING["420"]) in lib.calls
    encodes = [c for c in lib.calls if c[0] == "encode"]
    assert all(c[2:] == (nvjpeg.INPUT_RGBI, 6, 4, 55) for c in encodes)
    assert ("sync", 55) in lib.calls
    # pointers and row pitches (a frame without strides is packed: width * 3)
    assert sorted(lib.encoded.values()) == [(0x1000, 18), (0x2000, 32)]
    assert set(enc.seconds) == {"queueing", "waiting for the GPU", "copying out"}
    assert all(seconds >= 0 for seconds in enc.seconds.values())
    # a second call reuses the states and the parameters
    lib.calls.clear()
    assert enc.encode(frames, ImageSettings(width=6, height=4, quality=90), 55) == [JPEG, JPEG]
    assert not [c for c in lib.calls if c[0] in ("create", "params", "state")]


def test_a_large_pass_is_encoded_in_groups_each_waited_for_once(lib, monkeypatch):
    monkeypatch.setattr(nvjpeg, "GROUP", 2)
    enc = nvjpeg.NvJpeg(0)
    frames = Frames([Frame(0x1000 * (i + 1)) for i in range(5)])
    assert enc.encode(frames, ImageSettings(width=6, height=4), 9) == [JPEG] * 5
    kinds = [c[0] for c in lib.calls if c[0] in ("encode", "sync", "state")]
    assert kinds == ["state", "state"] + ["encode", "encode", "sync"] * 2 + ["encode", "sync"]
    assert sorted(p for p, _ in lib.encoded.values()) == [0x4000, 0x5000]  # the last group's


def test_close_frees_states_parameters_and_the_handle(lib):
    enc = nvjpeg.NvJpeg(0)
    enc.encode(Frames([Frame(0x1000), Frame(0x2000)]), ImageSettings(width=6, height=4), 3)
    lib.calls.clear()
    enc.close()
    assert sorted(c[0] for c in lib.calls) == [
        "destroy", "destroy params", "destroy state", "destroy state"
    ]  # fmt: skip
    lib.calls.clear()
    enc.close()  # twice: nothing left to free
    assert lib.calls == []


@pytest.mark.parametrize(
    "call", ["nvjpegCreateSimple", "nvjpegEncodeImage", "nvjpegEncodeRetrieveBitstream"]
)
def test_a_failing_call_is_an_error_naming_it(lib, call):
    lib.fail = call
    with pytest.raises(nvjpeg.NvJpegError, match=call):
        nvjpeg.NvJpeg(0).encode(Frames([Frame(0x1000)]), ImageSettings(width=6, height=4))


def test_a_malformed_jpeg_is_refused(monkeypatch):
    fake = StandIn(jpeg=b"\xff\xd8cut short")
    monkeypatch.setattr(nvjpeg, "load", lambda: (fake, fake))
    with pytest.raises(nvjpeg.NvJpegError, match="malformed"):
        nvjpeg.NvJpeg(0).encode(Frames([Frame(0x1000)]), ImageSettings(width=6, height=4))


@pytest.mark.parametrize(
    "frame, message",
    [
        (Frame(0x1000, typestr="<f4"), "uint8"),
        (Frame(0x1000, strides=(18, 1, 6)), "contiguous"),
    ],
)
def test_frames_it_cannot_encode_are_refused(lib, frame, message):
    with pytest.raises(nvjpeg.NvJpegError, match=message):
        nvjpeg.NvJpeg(0).encode(Frames([frame]), ImageSettings(width=6, height=4))


def test_without_the_library_it_is_unavailable_with_the_install_hint(monkeypatch):
    monkeypatch.setattr(nvjpeg, "_library", None)
    monkeypatch.setattr(nvjpeg, "LIBRARY_NAMES", ("libnvjpeg-not-here.so",) * 3)
    monkeypatch.setattr(nvjpeg.ctypes, "CDLL", _no_library)
    assert not nvjpeg.available()
    with pytest.raises(nvjpeg.NvJpegError, match="jpeg-cu13"):
        nvjpeg.load()


def _no_library(path):
    raise OSError(f"{path}: cannot open shared object file")


def test_the_renderer_lends_each_encode_an_encoder_of_its_own_and_reuses_them(monkeypatch):
    from vabench.render.warp_renderer import WarpRenderPool

    pool = WarpRenderPool(device="cpu", jpeg="nvjpeg")
    made: list[tuple] = []

    def new(urgent):
        made.append((f"encoder {len(made)}", 100 + len(made), urgent))
        return made[-1][:2]

    monkeypatch.setattr(pool, "_new_nvjpeg", new)
    with pool._device_encoder(False) as a, pool._device_encoder(False) as b:
        assert a != b  # two encodes at once: two encoders, each with its stream
    with pool._device_encoder(False) as c:
        assert c in (a, b)  # given back, then lent again
    with pool._device_encoder(True) as d:
        assert d not in (a, b)  # the critical path's: a stream of the greatest priority
    assert [m[2] for m in made] == [False, False, True]


def test_auto_falls_back_when_nvjpeg_loads_but_does_not_work(monkeypatch, caplog):
    """jpeg="auto" picks nvJPEG on a GPU; where its library loads but making an encoder
    fails (a system libnvjpeg too new for the driver) auto goes on to nvImageCodec or
    threads, while jpeg="nvjpeg" says why it cannot."""
    from vabench.render.images import RenderError
    from vabench.render.warp_renderer import WarpRenderPool

    def broken(urgent):
        raise nvjpeg.NvJpegError("nvjpegCreateSimple failed with nvjpegStatus_t 9")

    auto = WarpRenderPool(device="cpu", jpeg="auto")
    monkeypatch.setattr(auto, "_new_nvjpeg", broken)
    with caplog.at_level("WARNING"):
        assert auto._start_nvjpeg() is False
    assert "nvJPEG does not work here" in caplog.text and not auto._nvjpeg_pool[False]
    asked = WarpRenderPool(device="cpu", jpeg="nvjpeg")
    monkeypatch.setattr(asked, "_new_nvjpeg", broken)
    with pytest.raises(RenderError, match="nvjpegStatus_t 9"):
        asked._start_nvjpeg()
    working = WarpRenderPool(device="cpu", jpeg="auto")
    monkeypatch.setattr(working, "_new_nvjpeg", lambda urgent: ("encoder", 7))
    assert working._start_nvjpeg() is True
    assert working._nvjpeg_pool[False] == [("encoder", 7)]


def _jpeg_contention():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "jpeg_contention.py"
    spec = importlib.util.spec_from_file_location("jpeg_contention", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_benchmarks_slices_cover_every_frame_once_in_order():
    """`benchmarks/jpeg_contention.py --slices`: one call's frames cut into slices encoded side
    by side (measured on an H100: no faster, so only the benchmark has it)."""
    slice_bounds = _jpeg_contention().slice_bounds
    assert slice_bounds(25, 4) == [(0, 7), (7, 13), (13, 19), (19, 25)]
    assert slice_bounds(7, 4) == [(0, 7)]  # fewer than 2 x MIN_SLICE: one slice
    assert slice_bounds(8, 4) == [(0, 4), (4, 8)]
    for n in range(70):
        for k in range(1, 6):
            assert [i for a, b in slice_bounds(n, k) for i in range(a, b)] == list(range(n))


def test_the_benchmarks_slices_come_back_in_order_and_a_failure_waits_for_the_others():
    import time
    from concurrent.futures import ThreadPoolExecutor

    encode_in_slices = _jpeg_contention().encode_in_slices
    with ThreadPoolExecutor(3) as threads:
        got = encode_in_slices(lambda i, a, b: [bytes([k]) for k in range(a, b)], 16, 4, threads)
        assert got == [bytes([k]) for k in range(16)]
        ended: list[int] = []

        def encode(i, start, stop):
            if i == 0:
                raise RuntimeError("slice 0 failed")
            time.sleep(0.2)
            ended.append(i)
            return []

        with pytest.raises(RuntimeError, match="slice 0"):
            encode_in_slices(encode, 16, 4, threads)
        assert sorted(ended) == [1, 2, 3]  # none still reading the frames
