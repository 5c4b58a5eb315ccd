"""JPEG encoding on the GPU, from device memory, with NVIDIA's nvImageCodec (nvJPEG).

Where the Warp renderer runs on a GPU, its frames are already in device memory; nvImageCodec
encodes a whole batch there and only the JPEG bytes cross to the host (about a tenth of the
pixels). Install `nvidia-nvimgcodec-cu13` and `nvidia-nvjpeg` on a CUDA 13 host (the `-cu12`
wheel on CUDA 12). Without them the renderer copies the frames to the host and encodes them on
a thread pool (`images.JpegThreads`) with the same quality and chroma subsampling.
"""

from __future__ import annotations

import importlib.util
import time
from typing import Any

from vabench.render.images import ImageSettings

PACKAGE_HINT = "pip install 'vabench[jpeg-cu13]' (CUDA 13; jpeg-cu12 for CUDA 12)"


def available() -> bool:
    """Whether nvImageCodec can be imported (a GPU is checked when an encoder is made)."""
    try:
        return importlib.util.find_spec("nvidia.nvimgcodec") is not None
    except ModuleNotFoundError:  # no `nvidia` namespace at all
        return False


class DeviceJpeg:
    """Encodes (n, H, W, 3) uint8 frames in device memory of GPU `device_id` to JPEG bytes."""

    def __init__(self, device_id: int, threads: int = 0):
        """`threads`: the encoder's host threads (nvImageCodec's `max_num_cpu_threads`; 0, its
        default, is the host's cores less one). 1 (no pool) measured no better under load
        (benchmarks/jpeg_contention.py; docs/PERFORMANCE.md, "JPEG on the GPU")."""
        from nvidia import nvimgcodec

        self._nv = nvimgcodec
        self._encoder = nvimgcodec.Encoder(device_id=device_id, max_num_cpu_threads=threads)
        self._params: dict[tuple[int, str], Any] = {}
        self._outputs: list[Any] = []  # `_code_streams`
        self.seconds = {"making images": 0.0, "encoding": 0.0, "copying out": 0.0}
        """Where this encoder's calls spent their time (the renderer logs the sums)."""

    def _encode_params(self, settings: ImageSettings) -> Any:
        key = (settings.quality, settings.subsampling)
        if key not in self._params:
            nv = self._nv
            css = getattr(nv.ChromaSubsampling, f"CSS_{settings.subsampling}")
            self._params[key] = nv.EncodeParams(
                quality_type=nv.QualityType.QUALITY,
                quality_value=float(settings.quality),
                chroma_subsampling=css,
            )
        return self._params[key]

    def encode(
        self, frames: Any, settings: ImageSettings, cuda_stream: int | None = 0
    ) -> list[bytes]:
        """`frames`: anything indexable whose items expose `__cuda_array_interface__` (a Warp
        array of shape (n, H, W, 3)), complete or written by earlier work on `cuda_stream` (the
        handle of the stream the encode runs on; it returns once that stream has caught up).
        Warp reports the default stream's handle as None (a NULL pointer through ctypes), which
        nvImageCodec refuses: it is stream 0 to CUDA (every episode of a GPU sweep would fail
        on it)."""
        stream = int(cuda_stream or 0)
        t0 = time.perf_counter()
        # The image is tied to the encode's stream: by default nvImageCodec ties it to stream 0,
        # CUDA's legacy stream, which synchronises with every blocking stream of the process.
        images = [self._nv.as_image(frames[i], cuda_stream=stream) for i in range(frames.shape[0])]
        outputs = self._code_streams(len(images))
        t1 = time.perf_counter()
        streams = self._encoder.encode(
            images,
            "jpeg",
            code_stream_s=outputs,
            params=self._encode_params(settings),
            cuda_stream=stream,
        )
        t2 = time.perf_counter()
        if any(s is None for s in streams):
            raise RuntimeError("nvImageCodec failed to encode a frame")
        out = [_jpeg_bytes(s) for s in streams]
        seconds = self.seconds
        seconds["making images"] += t1 - t0
        seconds["encoding"] += t2 - t1
        seconds["copying out"] += time.perf_counter() - t2
        return out

    def _code_streams(self, n: int) -> list[Any]:
        """`n` output code streams, kept and reused from call to call. Left to nvImageCodec,
        every call made a new pinned host buffer for every image (and dropped the last call's),
        and allocating page-locked memory is one of CUDA's implicit synchronisations (the CUDA
        programming guide, "Implicit Synchronization"). A kept buffer grows to its largest
        image once. Measured in the suite: an encode's wall time did not change with it; what
        a JPEG call waits for under load is elsewhere (docs/PERFORMANCE.md, "JPEG on the
        GPU")."""
        while len(self._outputs) < n:
            self._outputs.append(self._nv.CodeStream(pre_allocated_size=0, pin_memory=True))
        return self._outputs[:n]


def _jpeg_bytes(code_stream: Any) -> bytes:
    """The JPEG of a code stream: its `size` bytes (a reused buffer may hold more: an earlier,
    larger image's tail, which also ends with an end-of-image marker), checked to start and end
    as a JPEG does: a frame cut short would otherwise reach the model without an error."""
    view = memoryview(code_stream)
    size = getattr(code_stream, "size", None)
    if not isinstance(size, int) or not 0 < size <= view.nbytes:
        raise RuntimeError(f"nvImageCodec reported no usable size for a JPEG ({size!r})")
    data = bytes(view[:size])  # the JPEG only, not the buffer's capacity
    if not (data.startswith(b"\xff\xd8") and data.endswith(b"\xff\xd9")):
        raise RuntimeError(f"nvImageCodec returned a malformed JPEG ({len(data)} bytes)")
    return data
