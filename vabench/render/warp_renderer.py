"""The Warp renderer: the images of many slots from one pass of MuJoCo Warp's batch ray tracer.

`WarpRenderPool` serves the engine's render requests (`RenderItem`: a slot's state, its object
model id and a camera pose) like the GL `RenderPool`, but on a GPU, all images of a request at
once:

1. every image is one world of a render batch: the item's state goes into that world's qpos,
   gathered on the device from the physics batch when the physics runs on Warp on the same
   device (`attach`; no trip through the host), else uploaded from the item's host copy. The
   passive bundle of a slot is five worlds with one state and five cameras;
2. kinematics of those worlds, then each world's camera is set to its item's pose and FOV
   (the model's FOV is batched per world, and rays are computed per world);
3. the BVH is refit and every world is ray traced in one launch (shadows, textures, skybox);
4. JPEG on the device with nvImageCodec where it is installed (`gpu_jpeg`), else the packed
   pixels come to the host and a thread pool encodes them (`images.JpegThreads`), with the
   quality and chroma subsampling of `ImageSettings` either way.

Render batches ("passes", `warp_pass.RenderPass`) are made per task family, image size and
world count (1, 2, 3, 4, 6, 8, 12, ...: `pass_size`), when first needed, and then reused: a
render context (BVHs, textures, buffers) and a model whose per-world fields hold each world's
object variant and FOV. A request larger than the largest pass the GPU's memory allows is
split into several passes, with a log message, never an out-of-memory crash.

Scene look: the same render model as the GL path (`renderer.render_spec`: visual geom groups
0-2, the scene's lights, materials and skybox; near and far planes as GL's), so images match
GL's to a few grey levels on average (tests/test_render_warp.py, docs/PERFORMANCE.md). Debug
overlays are drawn by GL only (`render_debug` says so).

On the CPU (`VABENCH_WARP_DEVICE=cpu`, tests) the same kernels run on Warp's CPU device.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np
import warp as wp

from vabench.render import gpu_jpeg
from vabench.render.images import (
    ImageSettings,
    JpegThreads,
    RenderError,
    RenderItem,
    RenderStats,
    packed_to_rgb,
)
from vabench.render.warp_pass import RenderPass, pass_bytes, pass_size, render_models
from vabench.sim_mjx.backends import device_lock, gpu_share, warp_device
from vabench.tasks import REGISTRY

log = logging.getLogger(__name__)

MIN_PASS = 8  # the smallest largest-pass a GPU must hold (else: memory too full to render)
MAX_PASS = 1024  # largest render batch on a GPU (memory permitting)
CPU_MAX_PASS = 64
MEMORY_SHARE = 0.4  # of the GPU memory free when a pass is sized; physics and JAX need the rest


@dataclass
class WarpRenderPool:
    """Renders model images of every task on one Warp device (see the module docstring).

    `device`: "cuda:N" or "cpu" (default: VABENCH_WARP_DEVICE, else cuda:0). `max_pass`: the
    most worlds one pass holds (default: from free GPU memory, at most MAX_PASS). `jpeg`:
    "auto" (nvImageCodec on a GPU where installed, else threads), "device" or "host".
    """

    device: str | None = None
    max_size: tuple[int, int] = (1280, 960)
    max_pass: int | None = None
    jpeg: str = "auto"
    jpeg_threads: int | None = None
    stats: RenderStats = field(default_factory=RenderStats)

    def __post_init__(self) -> None:
        if self.jpeg not in ("auto", "device", "host"):
            raise ValueError(f"jpeg must be 'auto', 'device' or 'host', got {self.jpeg!r}")
        self._device: Any = None
        self._passes: dict[tuple[str, int, int, int], RenderPass] = {}
        self._models: dict[str, list[mujoco.MjModel]] = {}
        self._sources: dict[str, Any] = {}
        self._largest: dict[tuple[int, int], int] = {}
        self._host_jpeg: JpegThreads | None = None
        self._device_jpeg: gpu_jpeg.DeviceJpeg | None = None
        self._lock = threading.Lock()  # one request at a time from this pool
        # The device's lock (shared with the physics batches of this process): every allocation
        # and copy on the device holds it (see sim_mjx.warp_batch, Threads).
        self._lock_device: threading.RLock | contextlib.nullcontext = contextlib.nullcontext()
        self.info: str | None = None

    # -- life cycle ----------------------------------------------------------------------
    def __enter__(self) -> WarpRenderPool:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def start(self) -> str:
        if self.info is not None:
            return self.info
        from vabench.render.backends import renderer_problem
        from vabench.sim_mjx.backends import BackendUnavailable

        name = self.device or warp_device()
        problem = renderer_problem(name)
        if problem is not None:
            raise BackendUnavailable(problem)
        self._device = wp.get_device(name)
        self._lock_device = device_lock(str(self._device))
        on_gpu = self._device.is_cuda
        if self.jpeg == "device" and not (on_gpu and gpu_jpeg.available()):
            raise RenderError(
                f"JPEG on the device needs a GPU and nvImageCodec: {gpu_jpeg.PACKAGE_HINT}"
            )
        if self.jpeg != "host" and on_gpu and gpu_jpeg.available():
            with self._lock_device:
                self._device_jpeg = gpu_jpeg.DeviceJpeg(self._device.ordinal)
        else:
            self._host_jpeg = JpegThreads(self.jpeg_threads)
        encoder = "nvImageCodec" if self._device_jpeg else f"{self._host_jpeg.threads} threads"  # type: ignore[union-attr]
        self.info = f"warp on {self._device} ({self._device.name}; JPEG: {encoder})"
        log.info("renderer: %s", self.info)
        return self.info

    def close(self) -> None:
        with self._lock, self._lock_device:  # freeing device memory is device work too
            self._passes.clear()
            self._sources.clear()
            if self._host_jpeg is not None:
                self._host_jpeg.close()
                self._host_jpeg = None

    # -- sharing the physics batch's memory -----------------------------------------------
    def attach(self, task: str, batch: Any) -> bool:
        """Read the states of `task`'s items with a slot from `batch` (a WarpBatch) on the
        device. Returns False (and renders from the items' host copies) when the batch is on
        another device or is not a Warp batch."""
        if self.info is None:
            self.start()
        if not hasattr(batch, "copy_qpos") or str(getattr(batch, "device", "")) != str(
            self._device
        ):
            return False
        self._sources[task] = batch
        return True

    def detach(self, task: str) -> None:
        self._sources.pop(task, None)

    # -- requests --------------------------------------------------------------------------
    def render(
        self, task: str, items: Sequence[RenderItem], settings: ImageSettings | None = None
    ) -> list[bytes]:
        """The model images: JPEG bytes for every item, in order (blocking; thread-safe)."""
        settings = settings or ImageSettings()
        return self._request(task, list(items), settings, encode=True)

    async def render_async(
        self, task: str, items: Sequence[RenderItem], settings: ImageSettings | None = None
    ) -> list[bytes]:
        return await asyncio.to_thread(self.render, task, items, settings)

    def render_rgb(
        self, task: str, items: Sequence[RenderItem], settings: ImageSettings | None = None
    ) -> np.ndarray:
        """The same images as (n, H, W, 3) uint8 RGB arrays (parity checks, contact sheets)."""
        settings = settings or ImageSettings()
        frames = self._request(task, list(items), settings, encode=False)
        return (
            np.concatenate(frames)
            if frames
            else np.zeros((0, settings.height, settings.width, 3), np.uint8)
        )

    def render_debug(self, task: str, items: Sequence[RenderItem], overlays: Any, settings=None):
        raise RenderError(
            "debug overlays (contacts, frames, markers) are drawn by the GL renderer: use "
            "RenderPool or `python -m vabench.render snapshot --debug`"
        )

    def _request(
        self, task: str, items: list[RenderItem], settings: ImageSettings, encode: bool
    ) -> list[Any]:
        if settings.width > self.max_size[0] or settings.height > self.max_size[1]:
            raise RenderError(
                f"image size {settings.width}x{settings.height} exceeds the renderer's maximum "
                f"{self.max_size[0]}x{self.max_size[1]}"
            )
        if not items:
            return []
        if self.info is None:
            self.start()
        models = self._task_models(task)
        nq = models[0].nq
        for it in items:
            if not 0 <= it.variant < len(models):
                raise RenderError(
                    f"variant {it.variant} out of range for {task} ({len(models)} object model ids)"
                )
            if np.shape(it.qpos) != (nq,):
                raise RenderError(f"qpos has shape {np.shape(it.qpos)}; {task} needs ({nq},)")
        source = self._sources.get(task)
        if source is not None and any(it.slot is None for it in items):
            source = None  # some items carry only their host state: use the host copies
        with self._lock:
            t0 = time.perf_counter()
            largest = self._largest_pass(settings)
            chunks = [items[i : i + largest] for i in range(0, len(items), largest)]
            if len(chunks) > 1:
                log.info(
                    "render request of %d images of %s split into %d passes of at most %d (%s)",
                    len(items),
                    task,
                    len(chunks),
                    largest,
                    "GPU memory" if self._device.is_cuda else "CPU",
                )
            out: list[Any] = []
            for chunk in chunks:
                out.extend(self._one_pass(task, models, chunk, settings, source, encode))
            self.stats.requests += 1
            self.stats.images += len(items)
        # JPEG off the critical path: host encodes run on the thread pool while the next
        # request (another task's, or this one's next pass) already draws.
        if out and isinstance(out[0], Future):
            done = [f.result() for f in out]
            out = [jpeg for jpeg, _ in done]
            self.stats.encode_s += sum(seconds for _, seconds in done)
        self.stats.wall_s += time.perf_counter() - t0
        return out

    def _one_pass(self, task, models, chunk, settings, source, encode) -> list[Any]:
        n = len(chunk)
        size = pass_size(n)
        device_jpeg = self._device_jpeg is not None
        with self._lock_device, wp.ScopedDevice(self._device):
            p = self._pass(
                task, models, min(size, self._largest_pass(settings)), settings, device_jpeg
            )
            t0 = time.perf_counter()
            p.draw(chunk, source)
            self.stats.passes += 1
            self.stats.shared_state += n if source is not None else 0
            if encode and self._device_jpeg is not None:
                rgb = p.rgb_on_device()
                stream = wp.get_stream(self._device).cuda_stream if self._device.is_cuda else 0
                t1 = time.perf_counter()
                images = self._device_jpeg.encode(rgb[:n], settings, stream)
                self.stats.render_s += t1 - t0
                self.stats.encode_s += time.perf_counter() - t1
                return images
            packed = p.packed(n)  # waits for the pass
        self.stats.render_s += time.perf_counter() - t0
        if not encode:
            return [packed_to_rgb(packed)]
        assert self._host_jpeg is not None
        bgrx = packed.view(np.uint8).reshape(n, settings.height, settings.width, 4)
        return self._host_jpeg.submit(bgrx, settings, colorspace="BGRX")

    # -- passes ----------------------------------------------------------------------------
    def _task_models(self, task: str) -> list[mujoco.MjModel]:
        if task not in self._models:
            if task not in REGISTRY:
                raise RenderError(f"unknown task {task!r}")
            self._models[task] = render_models(REGISTRY[task], *self.max_size)
        return self._models[task]

    def _largest_pass(self, settings: ImageSettings) -> int:
        """The most worlds of one pass at this image size: decided once per size (from the
        GPU memory free then), so that the passes built stay few."""
        key = (settings.width, settings.height)
        if key not in self._largest:
            self._largest[key] = self._fit(settings)
        return self._largest[key]

    def _fit(self, settings: ImageSettings) -> int:
        if self.max_pass is not None:
            return self.max_pass
        if not self._device.is_cuda:
            return CPU_MAX_PASS
        free = self._device.free_memory // gpu_share()
        fit = int(free * MEMORY_SHARE) // pass_bytes(
            settings.width, settings.height, 1, self._device_jpeg is not None
        )
        largest = 1 << max(0, min(MAX_PASS, fit).bit_length() - 1)  # a power of two
        if largest < MIN_PASS:
            raise RenderError(
                f"GPU memory is too full for a render pass of {settings.width}x{settings.height} "
                f"images ({free / 2**30:.1f} GiB free)"
            )
        return largest

    def _pass(self, task, models, n_worlds, settings, device_jpeg) -> RenderPass:
        key = (task, n_worlds, settings.width, settings.height)
        if key not in self._passes:
            self._passes[key] = RenderPass(
                models, n_worlds, settings.width, settings.height, device_jpeg
            )
        return self._passes[key]
