"""What both renderers share: the request and settings types, and JPEG encoding.

A model image is rendered by one of two backends (`vabench.render.backends`): the GL worker
processes (`worker.RenderPool`) or MuJoCo Warp's batch ray tracer on a GPU
(`warp_renderer.WarpRenderPool`). Both take the same `RenderItem`s and `ImageSettings` and
return JPEG bytes encoded here with the same quality and chroma subsampling, so a sweep's
images differ between backends only by what the two rasterisers draw.

Encoding uses libjpeg-turbo through `simplejpeg`, which releases the GIL: `JpegThreads`
encodes a batch on a thread pool, in order. (Pillow in a Python loop holds the GIL for part of
each image and was the encoder of the GL workers before; the GPU path can encode on the device
with nvImageCodec instead, `gpu_jpeg`.)
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Literal

import numpy as np
import simplejpeg

from vabench.children import usable_cores
from vabench.render.camera import CameraPose

Subsampling = Literal["444", "422", "420"]
SUBSAMPLINGS: tuple[str, ...] = ("444", "422", "420")


class RenderError(RuntimeError):
    """A render request that could not be served."""


@dataclass(frozen=True)
class RenderItem:
    """One image to make: a slot's state, its object model id, and the camera.

    `slot` (optional) is the simulator slot the state was read from: a renderer told to read
    states in the simulator's device memory (the Warp renderer with `state_on_device`, Warp
    physics on the same GPU) reads it there instead of `qpos`, the host copy every other path
    draws.
    """

    qpos: np.ndarray
    variant: int
    camera: CameraPose
    slot: int | None = None


@dataclass(frozen=True)
class ImageSettings:
    """Resolution and JPEG encoding of model images (FACTS: 1280x960, q95). `subsampling` is
    libjpeg's chroma subsampling: "420" (its default, half-resolution colour), "422", "444"."""

    width: int = 1280
    height: int = 960
    quality: int = 95
    subsampling: Subsampling = "420"

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not 1 <= self.quality <= 100:
            raise ValueError(f"JPEG quality must be in [1, 100], got {self.quality}")
        if self.subsampling not in SUBSAMPLINGS:
            raise ValueError(
                f"JPEG subsampling must be one of {SUBSAMPLINGS}, got {self.subsampling!r}"
            )


@dataclass
class RenderStats:
    requests: int = 0
    images: int = 0
    restarts: int = 0
    retries: int = 0
    passes: int = 0  # Warp: render passes (a request larger than the GPU holds takes several)
    shared_state: int = 0  # Warp: images whose state was read on the device from Warp physics
    built: int = 0  # Warp: render passes built (one kept serves later requests of up to its size)
    evicted: int = 0  # Warp: passes dropped to keep the passes kept within their memory budget
    build_s: float = 0.0  # Warp: building passes, the device's lock held (every batch waits)
    render_s: float = 0.0  # drawing and reading pixels (GL: inside workers)
    encode_s: float = 0.0  # JPEG encoding
    wall_s: float = 0.0  # around whole requests, in the caller


def encode_jpeg(
    pixels: np.ndarray, quality: int = 95, subsampling: str = "420", colorspace: str = "RGB"
) -> bytes:
    """JPEG bytes of one image: (H, W, 3) RGB, or (H, W, 4) with `colorspace` "BGRX" (the
    Warp renderer's packed 0x00RRGGBB pixels as little-endian bytes). Deterministic."""
    if not 1 <= quality <= 100:
        raise ValueError(f"JPEG quality must be in [1, 100], got {quality}")
    if subsampling not in SUBSAMPLINGS:
        raise ValueError(f"JPEG subsampling must be one of {SUBSAMPLINGS}, got {subsampling!r}")
    return simplejpeg.encode_jpeg(
        np.ascontiguousarray(pixels), quality, colorspace, subsampling, fastdct=False
    )


def packed_to_rgb(packed: np.ndarray) -> np.ndarray:
    """(..., H, W) uint32 pixels 0x??RRGGBB -> (..., H, W, 3) uint8 RGB."""
    bgrx = np.asarray(packed, np.uint32).view(np.uint8).reshape(*packed.shape, 4)
    return np.ascontiguousarray(bgrx[..., 2::-1])


class JpegThreads:
    """Encodes batches of frames on `threads` threads (default: half of this process's cores,
    `children.usable_cores`, at least 1; the physics and the model-call pool need the rest)."""

    def __init__(self, threads: int | None = None):
        self.threads = threads or max(1, usable_cores() // 2)
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="jpeg")

    def encode(
        self, frames: Sequence[np.ndarray] | np.ndarray, settings: ImageSettings, colorspace="RGB"
    ) -> list[bytes]:
        """JPEG bytes of every frame, in order."""
        q, s = settings.quality, settings.subsampling
        if len(frames) <= 1:
            return [encode_jpeg(f, q, s, colorspace) for f in frames]
        return list(self._pool.map(lambda f: encode_jpeg(f, q, s, colorspace), frames))

    def submit(
        self, frames: Sequence[np.ndarray] | np.ndarray, settings: ImageSettings, colorspace="RGB"
    ) -> list[Future[tuple[bytes, float]]]:
        """Start encoding every frame; each future gives (JPEG bytes, seconds it took). The
        frames must not change until the futures are done."""
        q, s = settings.quality, settings.subsampling

        def one(frame: np.ndarray) -> tuple[bytes, float]:
            t0 = time.perf_counter()
            return encode_jpeg(frame, q, s, colorspace), time.perf_counter() - t0

        return [self._pool.submit(one, f) for f in frames]

    def close(self) -> None:
        self._pool.shutdown(wait=True)
