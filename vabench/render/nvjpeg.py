"""JPEG on the GPU through nvJPEG itself, on the caller's CUDA stream (the Warp renderer's
`jpeg="nvjpeg"`, and auto's fallback on a GPU where its own kernels do not load: faster than
nvImageCodec in the suite, slower than the renderer's own kernels, `warp_jpeg`;
docs/PERFORMANCE.md, "JPEG on the GPU").

Why not nvImageCodec alone: it encodes on CUDA streams of its own, made at the default
priority, which is CUDA's lowest, the ray tracer's megakernels' too. Under load a pass's ~25
encodes waited behind other passes' megakernels, a call several times as long as on an idle
GPU for a few milliseconds of kernels; under a GPU load like the ray tracer's it made no call
where this module made 16 a second (benchmarks/jpeg_contention.py). Here every image is
encoded on the stream the caller
names (the renderer's encode stream, above the ray tracing in priority: `streams.PRIORITIES`),
each image with an encoder state of its own, so that a pass's encodes are queued back to back,
waited for once, then their bytes retrieved.

Each thread's encode holds its own encoder (the renderer keeps a pool: one an encode at once).
The library is the `nvidia-nvjpeg` wheel's `libnvjpeg.so.<CUDA major>` (installed with
`vabench[jpeg-cu13]`) or the system's; the stream is waited for through the CUDA driver
(`cuStreamSynchronize`). Every call's status is checked; a JPEG that does not start and end as
one is refused (as `gpu_jpeg` does).
"""

from __future__ import annotations

import ctypes
import glob
import os
import threading
import time
from typing import Any

from vabench.render.images import ImageSettings

INPUT_RGBI = 5  # nvjpegInputFormat_t: interleaved RGB
SUBSAMPLING = {"444": 0, "422": 1, "420": 2}  # nvjpegChromaSubsampling_t
LIBRARY_NAMES = ("libnvjpeg.so.13", "libnvjpeg.so.12", "libnvjpeg.so")
GROUP = 16
"""Images queued before the stream is waited for: each has an encoder state of its own, and a
state keeps device buffers of its largest image (a few MB at 1280x960), so a thread keeps at
most this many."""


class NvJpegError(RuntimeError):
    pass


class _Image(ctypes.Structure):
    """nvjpegImage_t: up to four planes, each a device pointer and a row pitch in bytes."""

    _fields_ = [("channel", ctypes.c_void_p * 4), ("pitch", ctypes.c_size_t * 4)]


_library: Any = None
_driver: Any = None
_load_lock = threading.Lock()


def _find_library() -> Any:
    """libnvjpeg from the `nvidia` wheels (nvidia/cu13/lib, nvidia/nvjpeg/lib) or the loader's
    path."""
    candidates: list[str] = []
    try:
        import nvidia

        for root in nvidia.__path__:
            for name in LIBRARY_NAMES[:2]:
                candidates += sorted(glob.glob(os.path.join(root, "**", name), recursive=True))
    except ImportError:
        pass
    candidates += list(LIBRARY_NAMES)
    problems = []
    for path in candidates:
        try:
            # CDLL: each call releases the interpreter's lock (~3 hand-offs an image, as
            # nvImageCodec's binding). Keeping it (PyDLL) would save them, but nvJPEG's calls
            # may block on the GPU (a first allocation syncs the device; parts of its pipeline
            # are synchronous), and a block with the lock held stops every thread of the
            # engine's process; the hand-offs did not bind in the main job (a shorter switch
            # interval changed nothing there: docs/PERFORMANCE.md, "JPEG on the GPU").
            return ctypes.CDLL(path)
        except OSError as err:
            problems.append(str(err))
    raise NvJpegError(
        "nvJPEG is not installed (pip install 'vabench[jpeg-cu13]'): " + "; ".join(problems[-2:])
    )


def load() -> tuple[Any, Any]:
    """(libnvjpeg, libcuda) with their signatures declared; loaded once a process."""
    global _library, _driver
    with _load_lock:
        if _library is None:
            lib = _find_library()
            vp, sz = ctypes.c_void_p, ctypes.c_size_t
            signatures = {
                "nvjpegCreateSimple": [ctypes.POINTER(vp)],
                "nvjpegEncoderStateCreate": [vp, ctypes.POINTER(vp), vp],
                "nvjpegEncoderParamsCreate": [vp, ctypes.POINTER(vp), vp],
                "nvjpegEncoderParamsSetQuality": [vp, ctypes.c_int, vp],
                "nvjpegEncoderParamsSetSamplingFactors": [vp, ctypes.c_int, vp],
                "nvjpegEncodeImage": [
                    vp,
                    vp,
                    vp,
                    ctypes.POINTER(_Image),
                    ctypes.c_int,
                    ctypes.c_int,
                    ctypes.c_int,
                    vp,
                ],
                "nvjpegEncodeRetrieveBitstream": [vp, vp, vp, ctypes.POINTER(sz), vp],
                "nvjpegEncoderStateDestroy": [vp],
                "nvjpegEncoderParamsDestroy": [vp],
                "nvjpegDestroy": [vp],
            }
            for name, argtypes in signatures.items():
                fn = getattr(lib, name)
                fn.argtypes, fn.restype = argtypes, ctypes.c_int
            driver = ctypes.CDLL("libcuda.so.1")
            driver.cuStreamSynchronize.argtypes = [vp]
            driver.cuStreamSynchronize.restype = ctypes.c_int
            _library, _driver = lib, driver
    return _library, _driver


def available() -> bool:
    """Whether libnvjpeg and the CUDA driver load."""
    try:
        load()
    except (NvJpegError, OSError, AttributeError):
        return False
    return True


def _check(status: int, call: str) -> None:
    if status != 0:
        raise NvJpegError(f"{call} failed with nvjpegStatus_t {status}")


class NvJpeg:
    """Encodes (n, H, W, 3) uint8 frames in device memory to JPEG bytes on a given CUDA stream.
    One instance a thread (its encoder states are reused from call to call); the handle is
    made on the device whose context is current when it is created (the renderer creates it
    with its device's lock held and Warp's device current)."""

    def __init__(self, device_id: int = 0):
        self._lib, self._driver = load()
        self.device_id = device_id
        self._handle = ctypes.c_void_p()
        _check(self._lib.nvjpegCreateSimple(ctypes.byref(self._handle)), "nvjpegCreateSimple")
        self._states: list[ctypes.c_void_p] = []
        self._params: dict[tuple[int, str], ctypes.c_void_p] = {}
        self.seconds = {"queueing": 0.0, "waiting for the GPU": 0.0, "copying out": 0.0}
        """Where this encoder's calls spent their time (the renderer logs the sums)."""

    def close(self) -> None:
        """Frees the encoder states, parameters and the handle (device memory among them)."""
        lib = self._lib
        for state in self._states:
            lib.nvjpegEncoderStateDestroy(state)
        for params in self._params.values():
            lib.nvjpegEncoderParamsDestroy(params)
        if self._handle:
            lib.nvjpegDestroy(self._handle)
        self._states, self._params, self._handle = [], {}, ctypes.c_void_p()

    def _encode_params(self, settings: ImageSettings, stream: int) -> ctypes.c_void_p:
        key = (settings.quality, settings.subsampling)
        if key not in self._params:
            params = ctypes.c_void_p()
            lib = self._lib
            _check(
                lib.nvjpegEncoderParamsCreate(self._handle, ctypes.byref(params), stream),
                "nvjpegEncoderParamsCreate",
            )
            _check(
                lib.nvjpegEncoderParamsSetQuality(params, settings.quality, stream),
                "nvjpegEncoderParamsSetQuality",
            )
            _check(
                lib.nvjpegEncoderParamsSetSamplingFactors(
                    params, SUBSAMPLING[settings.subsampling], stream
                ),
                "nvjpegEncoderParamsSetSamplingFactors",
            )
            self._params[key] = params
        return self._params[key]

    def _encoder_states(self, n: int, stream: int) -> list[ctypes.c_void_p]:
        while len(self._states) < n:
            state = ctypes.c_void_p()
            _check(
                self._lib.nvjpegEncoderStateCreate(self._handle, ctypes.byref(state), stream),
                "nvjpegEncoderStateCreate",
            )
            self._states.append(state)
        return self._states[:n]

    def encode(
        self, frames: Any, settings: ImageSettings, cuda_stream: int | None = 0
    ) -> list[bytes]:
        """`frames`: indexable, each item exposing `__cuda_array_interface__` of shape (H, W, 3)
        uint8 with rows contiguous (a Warp array's rows), written by earlier work on
        `cuda_stream` or complete. Returns once the stream has caught up."""
        stream = int(cuda_stream or 0)
        n = int(frames.shape[0])
        out: list[bytes] = []
        for start in range(0, n, GROUP):
            out += self._encode_group(frames, range(start, min(n, start + GROUP)), settings, stream)
        return out

    def _encode_group(
        self, frames: Any, indices: range, settings: ImageSettings, stream: int
    ) -> list[bytes]:
        t0 = time.perf_counter()
        params = self._encode_params(settings, stream)
        states = self._encoder_states(len(indices), stream)
        lib = self._lib
        keep = []  # the frames' views, alive until the stream has read them
        for state, i in zip(states, indices, strict=True):
            frame = frames[i]
            face = frame.__cuda_array_interface__
            height, width, channels = face["shape"]
            if channels != 3 or face["typestr"] != "|u1":
                raise NvJpegError(f"nvJPEG encodes (H, W, 3) uint8 frames, got {face['shape']}")
            strides = face.get("strides") or (width * 3, 3, 1)
            if strides[1:] != (3, 1):
                raise NvJpegError(f"nvJPEG needs each row's pixels contiguous, got {strides}")
            image = _Image()
            image.channel[0] = face["data"][0]
            image.pitch[0] = strides[0]
            keep.append((frame, image))
            _check(
                lib.nvjpegEncodeImage(
                    self._handle,
                    state,
                    params,
                    ctypes.byref(image),
                    INPUT_RGBI,
                    width,
                    height,
                    stream,
                ),
                "nvjpegEncodeImage",
            )
        t1 = time.perf_counter()
        status = self._driver.cuStreamSynchronize(stream)
        if status != 0:
            raise NvJpegError(f"cuStreamSynchronize failed with CUresult {status}")
        t2 = time.perf_counter()
        out = []
        for state in states:
            size = ctypes.c_size_t(0)
            _check(
                lib.nvjpegEncodeRetrieveBitstream(
                    self._handle, state, None, ctypes.byref(size), stream
                ),
                "nvjpegEncodeRetrieveBitstream",
            )
            buffer = (ctypes.c_ubyte * size.value)()
            _check(
                lib.nvjpegEncodeRetrieveBitstream(
                    self._handle, state, buffer, ctypes.byref(size), stream
                ),
                "nvjpegEncodeRetrieveBitstream",
            )
            data = ctypes.string_at(buffer, size.value)  # one copy, of the JPEG's own bytes
            if not (data.startswith(b"\xff\xd8") and data.endswith(b"\xff\xd9")):
                raise NvJpegError(f"nvJPEG returned a malformed JPEG ({len(data)} bytes)")
            out.append(data)
        del keep
        seconds = self.seconds
        seconds["queueing"] += t1 - t0
        seconds["waiting for the GPU"] += t2 - t1
        seconds["copying out"] += time.perf_counter() - t2
        return out
