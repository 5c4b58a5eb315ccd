"""What the device JPEG encoder hands nvImageCodec, and what it accepts back.

nvImageCodec needs a CUDA GPU, which this machine does not have: a stand-in module records the
calls (the real encoder runs in the GPU tests, `bash benchmarks/gpu/run.sh tests`, and in every
main job on the GPU). Checked: each image is tied to the encode's stream (not stream 0, CUDA's
legacy stream); the output code streams are kept and reused from call to call (a new pinned
buffer an image made every encode wait for the process's GPU work); a JPEG is returned cut to
its size and refused when it is not whole.
"""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

from vabench.render.images import ImageSettings

JPEG = b"\xff\xd8" + b"body" + b"\xff\xd9"


class _CodeStream:
    made = 0

    def __init__(self, pre_allocated_size: int = 0, pin_memory: bool = True):
        assert pin_memory
        _CodeStream.made += 1
        self.buffer = bytearray(pre_allocated_size)
        self.size = 0

    def __buffer__(self, flags):  # the buffer protocol (Python 3.12); 3.11: see _view
        return memoryview(self.buffer)


class _Encoder:
    def __init__(self, device_id: int, max_num_cpu_threads: int = 0):
        self.calls: list[dict] = []
        self.tail = b""

    def encode(self, images, codec, code_stream_s=None, params=None, cuda_stream=0):
        self.calls.append({"images": images, "outputs": code_stream_s, "stream": cuda_stream})
        for out in code_stream_s:
            data = JPEG + self.tail
            out.buffer[: len(data)] = data  # a reused buffer keeps its larger capacity
            out.size = len(JPEG)
        return code_stream_s


@pytest.fixture
def fake_nvimgcodec(monkeypatch):
    nv = types.ModuleType("nvidia.nvimgcodec")
    nv.Encoder = _Encoder
    nv.CodeStream = _CodeStream
    nv.as_image = lambda array, cuda_stream=0: ("image", array, cuda_stream)
    nv.EncodeParams = lambda **kw: kw
    nv.QualityType = types.SimpleNamespace(QUALITY="quality")
    nv.ChromaSubsampling = types.SimpleNamespace(CSS_420="420", CSS_444="444")
    package = types.ModuleType("nvidia")
    package.nvimgcodec = nv
    monkeypatch.setitem(sys.modules, "nvidia", package)
    monkeypatch.setitem(sys.modules, "nvidia.nvimgcodec", nv)
    _CodeStream.made = 0
    from vabench.render import gpu_jpeg

    monkeypatch.setattr(gpu_jpeg, "memoryview", _view, raising=False)
    return nv


def _view(obj):
    return memoryview(obj.buffer) if isinstance(obj, _CodeStream) else memoryview(obj)


def test_images_are_tied_to_the_encode_stream_and_outputs_are_reused(fake_nvimgcodec):
    from vabench.render.gpu_jpeg import DeviceJpeg

    jpeg = DeviceJpeg(0)
    frames = np.zeros((3, 4, 4, 3), np.uint8)
    first = jpeg.encode(frames, ImageSettings(4, 4, 95), cuda_stream=1234)
    assert first == [JPEG] * 3
    call = jpeg._encoder.calls[0]
    assert call["stream"] == 1234
    assert [image[2] for image in call["images"]] == [1234] * 3  # not CUDA's legacy stream 0
    jpeg._encoder.tail = b"tail of a larger image"
    second = jpeg.encode(frames[:2], ImageSettings(4, 4, 95), cuda_stream=1234)
    assert second == [JPEG] * 2  # cut to its size, not the buffer's capacity
    assert jpeg._encoder.calls[1]["outputs"] == call["outputs"][:2]  # the same buffers
    assert _CodeStream.made == 3


def test_a_jpeg_that_is_not_whole_is_refused(fake_nvimgcodec):
    from vabench.render.gpu_jpeg import DeviceJpeg

    jpeg = DeviceJpeg(0)

    def broken(images, codec, code_stream_s=None, params=None, cuda_stream=0):
        for out in code_stream_s:
            out.buffer[:4] = b"\xff\xd8ab"  # cut short: no end-of-image marker
            out.size = 4
        return code_stream_s

    jpeg._encoder.encode = broken
    with pytest.raises(RuntimeError, match="malformed JPEG"):
        jpeg.encode(np.zeros((1, 4, 4, 3), np.uint8), ImageSettings(4, 4, 95), cuda_stream=7)

    def unsized(images, codec, code_stream_s=None, params=None, cuda_stream=0):
        for out in code_stream_s:  # a whole JPEG then an earlier image's tail, size unknown
            out.buffer[:] = JPEG + b"tail" + b"\xff\xd9"
            out.size = None
        return code_stream_s

    jpeg._encoder.encode = unsized
    with pytest.raises(RuntimeError, match="no usable size"):
        jpeg.encode(np.zeros((1, 4, 4, 3), np.uint8), ImageSettings(4, 4, 95), cuda_stream=7)
