"""The Warp renderer: the images of many slots from one pass of MuJoCo Warp's batch ray tracer.

`WarpRenderPool` serves the engine's render requests (`RenderItem`: a slot's state, its object
model id and a camera pose) like the GL `RenderPool`, but on a GPU, all images of a request at
once:

1. every image is one world of a render batch: the item's state goes into that world's qpos,
   uploaded from the item's host copy (or, with `state_on_device`, gathered on the device from
   the Warp physics batch the request names). The passive bundle of a slot is five worlds
   with one state and five cameras;
2. kinematics of those worlds, then each world's camera is set to its item's pose and FOV
   (the model's FOV is batched per world, and rays are computed per world);
3. the BVH is refit and every world is ray traced in one launch (shadows, textures, skybox);
4. JPEG on the device: by each pass's own Warp kernels, queued right behind its ray tracing
   (`warp_jpeg`, two waits a pass, no library; the default on a GPU), else with nvJPEG on the
   renderer's own priority streams (`nvjpeg`), else nvImageCodec where it is installed
   (`gpu_jpeg`), else the packed pixels come to the host and a thread pool encodes them
   (`images.JpegThreads`), with the quality and chroma subsampling of `ImageSettings` every
   way (`JPEG_CHOICES`).

Render batches ("passes", `warp_pass.RenderPass`) are made per task family, image size and
world count (1, 2, 3, 4, 6, 8, 12, ...: `pass_size`), when first needed, and then reused: a
render context (BVHs, textures, buffers) and a model whose per-world fields hold each world's
object variant and FOV. A request larger than the largest pass the GPU's memory allows is
split into several passes, with a log message, never an out-of-memory crash. The passes kept
share one memory budget (`MEMORY_SHARE` of the GPU's free memory when the first is sized): a
pass that would not fit evicts the least recently used ones. Without it a sweep's memory grew
with every task family and request size it met until the GPU ran out (CUDA out-of-memory
errors within minutes of a suite).

Threads and streams: requests of several tasks run at once (each task's render service has a
thread of its own). A request takes a pass for itself (`RenderPass.lock`), queues the pass on
the pass's CUDA stream holding the device's lock (the states uploaded from the items' host
copies; with `state_on_device`, gathered on the physics batch's stream, ordered between its
actions: `WarpBatch.copy_qpos`), waits for it with the lock released, and encodes its JPEGs
on an encoder lent for the encode (nvJPEG) or the thread's own (nvImageCodec) while other
passes trace and the physics steps
(`sim_mjx.warp.streams`). The pool's own lock guards only the
passes kept and the counters; a pass is built outside it, one at a time.

The physics batch to read states from is named per request (`source`), not registered per
task: one process may run two batches of one task at once (a Ray engine runs several cells),
and each request's slots index its own batch.

Scene look: the same render model as the GL path (`renderer.render_spec`: visual geom groups
0-2, the scene's lights, materials and skybox; near and far planes as GL's), so images match
GL's to a few grey levels on average (tests/test_render_warp.py; docs/PERFORMANCE.md,
"Renderer"). Debug
overlays are drawn by GL only (`render_debug` says so).

On the CPU (`VABENCH_WARP_DEVICE=cpu`, tests) the same kernels run on Warp's CPU device.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np
import warp as wp

from vabench import switches
from vabench.render import gpu_jpeg, nvjpeg, warp_jpeg, warp_scan
from vabench.render.images import (
    ImageSettings,
    JpegThreads,
    RenderError,
    RenderItem,
    RenderStats,
    packed_to_rgb,
)
from vabench.render.warp_pass import RenderPass, pass_bytes, pass_size, render_models
from vabench.sim_mjx.warp import streams
from vabench.sim_mjx.warp.device import device_lock, gpu_share, warp_device
from vabench.sim_mjx.warp.model import RENDER_IGNORED, VariantFields, variant_fields
from vabench.tasks import REGISTRY

log = logging.getLogger(__name__)

JPEG_CHOICES = ("auto", "device", "host", "nvjpeg", "kernels")
"""`WarpRenderPool.jpeg`: auto (on a GPU each pass's own Warp kernels, falling back to nvJPEG
where they do not load, then nvImageCodec where installed, then host threads; on the CPU host
threads), kernels (`vabench.render.warp_jpeg`: two waits a pass instead of nvJPEG's waits in
every frame; on any Warp device, no library needed), nvjpeg (nvJPEG on the renderer's own
priority streams, `vabench.render.nvjpeg`, or an error), device (nvImageCodec or an error),
host (threads). The environment's VABENCH_WARP_JPEG sets the default (for measuring side by
side).

The kernels first: beside a ray-tracer-like GPU load they make several times nvJPEG's calls,
and the suite ends sooner with them (docs/PERFORMANCE.md, "JPEG on the GPU"): nvJPEG sizes each
frame's output on the host, so every frame waits behind the other passes' kernels. nvJPEG
before nvImageCodec, which encodes on streams of its own at CUDA's lowest priority, behind the
ray tracer's kernels, and hands the interpreter's lock back and forth in every image."""
MIN_PASS = 8  # the smallest largest-pass a GPU must hold (else: memory too full to render)
MAX_PASS = 1024  # largest render batch on a GPU (memory permitting)
MAX_PASS_PIXELS = 128 * 1280 * 960
"""Largest render batch on a GPU in pixels (128 worlds at 1280x960, ~1.1 GB): the passes of
many tasks are in use at once (each on its own stream), so they must fit the budget together;
larger requests take several passes, which the GPU traces beside other tasks' passes."""
CPU_MAX_PASS = 64
MEMORY_SHARE = 0.4  # of the GPU memory free when the first pass is sized: all passes kept
CPU_BUDGET_WORLDS = 2 * CPU_MAX_PASS  # the pass budget on the CPU, in worlds of the largest size


NO_DEVICE_JPEG = (
    "renderer: JPEG on CPU threads, not on the GPU: neither nvJPEG nor nvImageCodec loads (%s). "
    "JPEG on the host's cores is several times slower at 1280x960 "
    "(docs/PERFORMANCE.md, 'Renderer')"
)


@dataclass
class WarpRenderPool:
    """Renders model images of every task on one Warp device (see the module docstring).

    `device`: "cuda:N" or "cpu" (default: VABENCH_WARP_DEVICE, else cuda:0). `max_pass`: the
    most worlds one pass holds (default: from free GPU memory, at most MAX_PASS). `jpeg`:
    "auto" (on a GPU the passes' own Warp kernels, else nvJPEG, else nvImageCodec where
    installed, else threads), "kernels", "nvjpeg", "device" (nvImageCodec) or "host"
    (`JPEG_CHOICES`). `memory_budget`: bytes all passes
    kept may take (default: MEMORY_SHARE of the GPU memory free when the first pass is sized;
    on the CPU, CPU_BUDGET_WORLDS worlds of the largest size).
    """

    device: str | None = None
    max_size: tuple[int, int] = (1280, 960)
    max_pass: int | None = None
    jpeg: str = field(default_factory=lambda: str(switches.get("warp_jpeg")))
    jpeg_threads: int | None = None
    memory_budget: int | None = None
    state_on_device: bool = False
    """Read each image's state from the Warp physics batch a request names (`source`) on the
    device, instead of uploading the host copy every `RenderItem` carries. Off by default: the
    gather is queued on the batch's stream after every action already queued there
    (`WarpBatch.copy_qpos`), so a group of episodes' images waited for another group's whole
    action (the basket's episodes drift into ~3 groups a round; its action takes ~0.4 s in
    the suite); the upload is a few kB a pass."""
    concurrent_requests: int = field(
        default_factory=lambda: int(switches.get("render_concurrency"))
    )
    """Requests of one task an engine sends side by side (`RenderService`; default 1, or the
    environment's VABENCH_RENDER_CONCURRENCY). With more than one, a pass's frames are copied
    on the device after its ray tracing and the pass is free for the next request while they
    are encoded: the basket's episodes drift into ~2.4 groups a round, and each group's images
    wait for the others' requests. Measured: 2 no faster in the suite (docs/PERFORMANCE.md,
    "JPEG on the GPU"), so 1 stays the default and the simpler path."""
    stats: RenderStats = field(default_factory=RenderStats)

    def __post_init__(self) -> None:
        if self.concurrent_requests < 1:
            raise ValueError(f"concurrent_requests must be >= 1, got {self.concurrent_requests}")
        if self.jpeg not in JPEG_CHOICES:
            raise ValueError(f"jpeg must be one of {JPEG_CHOICES}, got {self.jpeg!r}")
        self._device: Any = None
        # Passes kept, least recently used first, with the bytes each was charged.
        # (task, worlds, width, height) -> (pass, bytes charged)
        self._passes: OrderedDict[tuple[str, int, int, int], tuple[RenderPass, int]] = OrderedDict()
        self._budget = self.memory_budget  # bytes for all passes kept (else set with the first)
        self._models: dict[str, list[mujoco.MjModel]] = {}
        # per task, the model fields its variants differ in (found by the first pass built)
        self._variants: dict[str, VariantFields] = {}
        self._largest: dict[tuple[int, int], int] = {}
        self._host_jpeg: JpegThreads | None = None
        # set where JPEG is encoded on the device (nvImageCodec's first encoder, or nvjpeg's
        # first pooled (encoder, stream)): the passes then keep their RGB on the device
        self._device_jpeg: Any = None
        self._lock = threading.Lock()  # the passes kept, their budget and the stats
        self._building = threading.Lock()  # one pass built at a time, outside `_lock`
        self._encoders = threading.local()
        # with nvJPEG: encoders (each with its stream) not in use, per priority (urgent or
        # not), taken by a pass for its encode and given back: as many as encode at once
        self._nvjpeg_pool: dict[bool, list[tuple[nvjpeg.NvJpeg, int]]] = {False: [], True: []}
        self._device_encoders: list[Any] = []  # every device encoder made (their `seconds`)
        self._nvjpeg = self.jpeg == "nvjpeg"  # resolved by `start` (jpeg="auto": on a GPU)
        self._warp_jpeg_seconds: dict[str, float] = {}  # the passes' own encoders' (kernels)
        self._kernels = self.jpeg == "kernels"  # resolved by `start` (jpeg="auto": on a GPU)
        # The device's lock (shared with the physics batches of this process): every allocation
        # and copy on the device holds it (see sim_mjx.warp_batch, Threads).
        self._lock_device: contextlib.AbstractContextManager[Any] = contextlib.nullcontext()
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
        from vabench.render.availability import renderer_problem
        from vabench.sim_mjx.backends import BackendUnavailable

        name = self.device or warp_device()
        problem = renderer_problem(name)
        if problem is not None:
            raise BackendUnavailable(problem)
        self._device = wp.get_device(name)
        self._lock_device = device_lock(str(self._device))
        on_gpu = self._device.is_cuda
        self._kernels = self.jpeg == "kernels" or (self.jpeg == "auto" and on_gpu)
        if self._kernels and self._start_kernels():
            self.info = f"warp on {self._device} ({self._device.name}; JPEG: Warp kernels a pass)"
            log.info("renderer: %s", self.info)
            return self.info
        if self.jpeg == "device" and not (on_gpu and gpu_jpeg.available()):
            raise RenderError(
                f"JPEG on the device needs a GPU and nvImageCodec: {gpu_jpeg.PACKAGE_HINT}"
            )
        if self.jpeg == "nvjpeg" and not (on_gpu and nvjpeg.available()):
            raise RenderError(f"jpeg='nvjpeg' needs a GPU and nvJPEG: {gpu_jpeg.PACKAGE_HINT}")
        wants_nvjpeg = self.jpeg == "nvjpeg" or (
            self.jpeg == "auto" and on_gpu and nvjpeg.available()
        )
        self._nvjpeg = wants_nvjpeg and self._start_nvjpeg()
        if not self._nvjpeg:
            self._start_other_jpeg(on_gpu)
        encoder = (
            ("nvJPEG on the renderer's streams" if self._nvjpeg else "nvImageCodec")
            if self._device_jpeg
            else f"{self._host_jpeg.threads} threads"  # type: ignore[union-attr]
        )
        self.info = f"warp on {self._device} ({self._device.name}; JPEG: {encoder})"
        log.info("renderer: %s", self.info)
        return self.info

    def _start_kernels(self) -> bool:
        """The JPEG kernels' modules compiled or loaded now (not in the first pass's hold of
        the device's lock); False where jpeg="auto" and they fail to (auto then goes on to
        nvJPEG)."""
        try:
            with self._lock_device:
                warp_jpeg.load_modules(self._device)
                wp.load_module(warp_scan, device=self._device)
        except Exception as err:  # a compiler or driver error: Warp raises plain exceptions
            if self.jpeg == "kernels":
                raise RenderError(f"jpeg='kernels': the JPEG kernels do not load: {err}") from err
            log.warning("renderer: the JPEG kernels do not load (%s); trying nvJPEG", err)
            self._kernels = False
            return False
        return True

    def _start_nvjpeg(self) -> bool:
        """The first nvJPEG encoder made and pooled; False where jpeg="auto" and the library
        loads but does not work here (a system libnvjpeg too new for the driver): auto then
        goes on to nvImageCodec or threads."""
        try:
            self._device_jpeg = self._new_nvjpeg(False)
        except nvjpeg.NvJpegError as err:
            if self.jpeg == "nvjpeg":
                raise RenderError(f"jpeg='nvjpeg': {err}") from err
            log.warning("renderer: nvJPEG does not work here (%s); trying nvImageCodec", err)
            return False
        self._nvjpeg_pool[False].append(self._device_jpeg)
        return True

    def _start_other_jpeg(self, on_gpu: bool) -> None:
        """Without nvJPEG: nvImageCodec's first encoder on a GPU where installed (unless
        jpeg="host"), else the host's threads (with a warning where auto found neither)."""
        if self.jpeg != "host" and on_gpu and gpu_jpeg.available():
            with self._lock_device:
                self._device_jpeg = gpu_jpeg.DeviceJpeg(self._device.ordinal)
            return
        self._host_jpeg = JpegThreads(self.jpeg_threads)
        if on_gpu and self.jpeg == "auto":
            log.warning(NO_DEVICE_JPEG, gpu_jpeg.PACKAGE_HINT)

    def close(self) -> None:
        st = self.stats
        if st.requests:
            log.info(
                "renderer: %d requests, %d images in %d passes (%d built in %.1f s with the "
                "device's lock held, %d evicted); %.1f s drawing, %.1f s JPEG, %.1f s in requests",
                st.requests,
                st.images,
                st.passes,
                st.built,
                st.build_s,
                st.evicted,
                st.render_s,
                st.encode_s,
                st.wall_s,
            )
        parts: dict[str, float] = {}
        for encoder in self._device_encoders:
            for part, seconds in encoder.seconds.items():
                parts[part] = parts.get(part, 0.0) + seconds
        with warp_jpeg.SECONDS_LOCK:
            for part, seconds in self._warp_jpeg_seconds.items():
                parts[part] = parts.get(part, 0.0) + seconds
        if parts:
            log.info(
                "renderer: JPEG on the device: %s",
                ", ".join(f"{seconds:.1f} s {part}" for part, seconds in parts.items()),
            )
        with self._lock, self._lock_device:  # freeing device memory is device work too
            for p, _ in self._passes.values():
                p.evicted = True
            self._passes.clear()
            if self._host_jpeg is not None:
                self._host_jpeg.close()
                self._host_jpeg = None
            for pool in self._nvjpeg_pool.values():
                while pool:
                    with self._device.context_guard:
                        pool.pop()[0].close()

    # -- sharing the physics batch's memory -----------------------------------------------
    def shares(self, batch: Any) -> bool:
        """Whether this pool can read states from `batch` on the device (a Warp physics batch
        on the same device): then pass it as `source` with the requests of its slots (the pool
        reads them there with `state_on_device`; a source on the critical path also gets its
        passes the highest stream priority)."""
        if self.info is None:
            self.start()
        return hasattr(batch, "copy_qpos") and str(getattr(batch, "device", "")) == str(
            self._device
        )

    # -- requests --------------------------------------------------------------------------
    def render(
        self,
        task: str,
        items: Sequence[RenderItem],
        settings: ImageSettings | None = None,
        source: Any = None,
    ) -> list[bytes]:
        """The model images: JPEG bytes for every item, in order (blocking; thread-safe).
        `source`: the physics batch the items' slots index, read on the device where this pool
        `shares` it (else, or without it, the items' host copies are drawn)."""
        settings = settings or ImageSettings()
        return self._request(task, list(items), settings, True, source)

    async def render_async(
        self,
        task: str,
        items: Sequence[RenderItem],
        settings: ImageSettings | None = None,
        source: Any = None,
    ) -> list[bytes]:
        return await asyncio.to_thread(self.render, task, items, settings, source)

    def render_rgb(
        self,
        task: str,
        items: Sequence[RenderItem],
        settings: ImageSettings | None = None,
        source: Any = None,
    ) -> np.ndarray:
        """The same images as (n, H, W, 3) uint8 RGB arrays (parity checks, contact sheets)."""
        settings = settings or ImageSettings()
        frames = self._request(task, list(items), settings, False, source)
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
        self, task: str, items: list[RenderItem], settings: ImageSettings, encode: bool, source: Any
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
        if source is not None and (not self.shares(source) or any(it.slot is None for it in items)):
            source = None  # another device, or items with only their host state: host copies
        t0 = time.perf_counter()
        with self._lock:
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
        with self._lock:
            self.stats.requests += 1
            self.stats.images += len(items)
        # JPEG off the critical path: host encodes run on the thread pool while the next
        # request (another task's, or this one's next pass) already draws.
        if out and isinstance(out[0], Future):
            done = [f.result() for f in out]
            out = [jpeg for jpeg, _ in done]
            with self._lock:
                self.stats.encode_s += sum(seconds for _, seconds in done)
        with self._lock:
            self.stats.wall_s += time.perf_counter() - t0
        return out

    def _one_pass(self, task, models, chunk, settings, source, encode) -> list[Any]:
        """One pass of up to `largest` images: queued on the pass's stream under the device
        lock, waited for without it, then encoded (nvJPEG or nvImageCodec on the device, or the
        host's threads): the GPU traces other tasks' passes and steps the physics meanwhile."""
        n = len(chunk)
        kind = self._jpeg_kind
        urgent = bool(getattr(source, "critical_path", False))  # see WarpBatch
        p = self._checkout(task, models, pass_size(n), settings, kind, urgent)
        locked = True
        try:
            t0 = time.perf_counter()
            with streams.queueing(self._lock_device, self._device, p.stream):
                p.draw(chunk, source if self.state_on_device else None)
                pending = None
                if encode and p.jpeg is not None:  # queued behind the ray tracing at once
                    after = streams.record(p.stream)
                    pending = p.jpeg.queue(p.rc.rgb_data, n, settings, after)
                rgb = p.rgb_on_device() if encode and kind is True else None
                copied = rgb is not None and self.concurrent_requests > 1
                if rgb is not None and copied:  # on the pass's stream: see concurrent_requests
                    rgb = wp.clone(rgb[:n])
                if rgb is None and pending is None:
                    p.queue_packed()
                done = streams.record(p.stream)
            streams.wait(done)
            t1 = time.perf_counter()
            if pending is not None:  # the pass stays locked: its encoder's buffers are in use
                assert p.jpeg is not None
                images = p.jpeg.finish(
                    pending, lambda: streams.queueing(self._lock_device, self._device, None)
                )
                self._count(n, source, t1 - t0, time.perf_counter() - t1)
                return images
            if copied:  # the pass's pixels are copied: the next request may draw
                p.lock.release()
                locked = False
            if rgb is not None:  # its pixels are on the device: the wait above saw them
                # the device's context current for this thread (nvJPEG's runtime calls use it)
                with (
                    self._device_encoder(urgent) as (encoder, stream),
                    streams.failing_device(),
                    self._device.context_guard,
                ):
                    images = encoder.encode(rgb[:n], settings, stream)
                if copied:
                    with self._lock_device:  # freeing device memory is device work too
                        del rgb
                self._count(n, source, t1 - t0, time.perf_counter() - t1)
                return images
            packed = p.packed(n)
        finally:
            if locked:
                p.lock.release()
        self._count(n, source, t1 - t0, 0.0)
        if not encode:
            return [packed_to_rgb(packed)]
        assert self._host_jpeg is not None
        bgrx = packed.view(np.uint8).reshape(n, settings.height, settings.width, 4)
        return self._host_jpeg.submit(bgrx, settings, colorspace="BGRX")

    def _count(self, n: int, source: Any, render_s: float, encode_s: float) -> None:
        with self._lock:
            self.stats.passes += 1
            self.stats.shared_state += n if source is not None and self.state_on_device else 0
            self.stats.render_s += render_s
            self.stats.encode_s += encode_s

    @property
    def _jpeg_kind(self) -> bool | str:
        """What a pass keeps for its JPEG (`RenderPass`'s `device_jpeg`)."""
        return "kernels" if self._kernels else self._device_jpeg is not None

    @contextlib.contextmanager
    def _device_encoder(self, urgent: bool) -> Iterator[tuple[Any, int]]:
        """An encoder on the device and the handle of its stream, for one encode: with
        nvJPEG one taken from the pool (or made) and given back after; else this
        thread's nvImageCodec encoder (`_jpeg_encoder`)."""
        if not self._nvjpeg:
            yield self._jpeg_encoder(urgent)
            return
        with self._lock:
            pool = self._nvjpeg_pool[urgent]
            taken = pool.pop() if pool else None
        if taken is None:
            taken = self._new_nvjpeg(urgent)
        try:
            yield taken
        finally:
            with self._lock:
                self._nvjpeg_pool[urgent].append(taken)

    def _new_nvjpeg(self, urgent: bool) -> tuple[nvjpeg.NvJpeg, int]:
        """An nvJPEG encoder and a stream of its own, above the ray tracing in priority (the
        critical path's highest)."""
        with self._lock_device, self._device.context_guard:
            stream = streams.new_stream(self._device, "greatest" if urgent else "middle")
            encoder = nvjpeg.NvJpeg(self._device.ordinal)
        with self._lock:
            self._device_encoders.append(encoder)
        return encoder, stream.cuda_stream if stream is not None else 0

    def _jpeg_encoder(self, urgent: bool) -> tuple[Any, int]:
        """This thread's nvImageCodec encoder (one per thread: passes of several tasks encode
        at once, and an encoder is not shared between threads) and the handle of this thread's
        stream to encode on: above the passes' ray tracing in priority, the critical path's
        highest (`streams.PRIORITIES`: each of the encode's small kernels waited behind the
        pending blocks of other passes' megakernels, ~0.25 s a call for ~3 ms of kernels)."""
        local = self._encoders
        if getattr(local, "jpeg", None) is None:
            local.jpeg = {}
        if urgent not in local.jpeg:  # an encoder a stream: nvJPEG's state follows its stream
            with self._lock_device:
                stream = streams.new_stream(self._device, "greatest" if urgent else "middle")
                encoder = gpu_jpeg.DeviceJpeg(self._device.ordinal)
            with self._lock:
                self._device_encoders.append(encoder)
            local.jpeg[urgent] = (encoder, stream.cuda_stream if stream is not None else 0)
        return local.jpeg[urgent]

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
            settings.width, settings.height, 1, self._jpeg_kind, settings.subsampling
        )
        cap = min(MAX_PASS, MAX_PASS_PIXELS // (settings.width * settings.height))
        largest = 1 << max(0, min(cap, fit).bit_length() - 1)  # a power of two
        if largest < MIN_PASS:
            raise RenderError(
                f"GPU memory is too full for a render pass of {settings.width}x{settings.height} "
                f"images ({free / 2**30:.1f} GiB free)"
            )
        return largest

    def _checkout(self, task, models, n_worlds, settings, device_jpeg, urgent) -> RenderPass:
        """A pass for `n_worlds` images of `task`, locked for the caller (who releases
        `pass.lock`): a kept pass of this key, waited for if another request uses it, else one
        built within the memory budget. The pool's lock is held only to look up and update the
        passes kept: building a pass (a render context, seconds on a fresh GPU) happens outside
        it, one build at a time, so that requests for passes already built go on meanwhile."""
        while True:
            with self._lock:
                n_worlds = min(n_worlds, self._largest_pass(settings))
                p = self._kept(task, n_worlds, settings)
                if p is not None and p.lock.acquire(blocking=False):
                    return p
            if p is not None:
                with p.lock:  # in use by another request: wait for it, outside the pool's lock
                    pass
                continue  # then look again: it may have been evicted meanwhile
            with self._building:
                with self._lock:
                    if self._kept(task, n_worlds, settings) is not None:
                        continue  # built by another request while this one waited to build
                built = self._build(task, models, n_worlds, settings, device_jpeg, urgent)
                built.lock.acquire()
                return built

    def _kept(self, task, n_worlds, settings) -> RenderPass | None:
        """A kept pass that serves `n_worlds` images of `task` (the caller holds the pool's
        lock). One of up to twice the worlds serves too (the extra worlds are traced
        for nothing): under a tight budget, building a pass per request size would churn."""
        kept = [
            k
            for k in self._passes
            if k[0] == task
            and k[2:4] == (settings.width, settings.height)
            and n_worlds <= k[1] <= 2 * n_worlds
        ]
        if not kept:
            return None
        best = min(kept, key=lambda k: k[1])
        self._passes.move_to_end(best)
        return self._passes[best][0]

    def _build(self, task, models, n_worlds, settings, device_jpeg, urgent) -> RenderPass:
        """A new pass, kept, after evicting least recently used passes not in use until it fits
        the memory budget (the caller holds `_building`)."""
        key = (task, n_worlds, settings.width, settings.height)
        need = pass_bytes(
            settings.width, settings.height, n_worlds, device_jpeg, settings.subsampling
        )
        victims = []
        with self._lock:
            budget = self._pass_budget(settings)
            for old in list(self._passes):
                if self.bytes_kept() + need <= budget:
                    break
                victim = self._passes[old][0]
                if not victim.lock.acquire(blocking=False):
                    continue  # in use: try the next least recently used
                victim.evicted = True
                del self._passes[old]
                victim.lock.release()
                victims.append(victim)
                self.stats.evicted += 1
                log.debug("render pass %s evicted for %s (budget %d MiB)", old, key, budget >> 20)
        with self._lock_device, wp.ScopedDevice(self._device):
            t0 = time.perf_counter()
            victims.clear()  # their memory is freed here, with the device's lock held
            if task not in self._variants:  # once a family, not once a pass
                self._variants[task] = variant_fields(models, RENDER_IGNORED)
            built = RenderPass(
                models,
                n_worlds,
                settings.width,
                settings.height,
                device_jpeg,
                urgent,
                self._warp_jpeg_seconds,
                self._variants[task],
            )
            seconds = time.perf_counter() - t0
        with self._lock:
            self._passes[key] = (built, need)
            self.stats.built += 1
            self.stats.build_s += seconds
        return built

    def bytes_kept(self) -> int:
        """Device memory charged to the passes kept (their pixels and per-world margin)."""
        return sum(charged for _, charged in self._passes.values())

    def _pass_budget(self, settings: ImageSettings) -> int:
        """Bytes all passes kept may take: decided with the first pass (from the memory free
        then, like the largest pass), and never less than the largest pass of any size."""
        w, h, jpeg, sub = settings.width, settings.height, self._jpeg_kind, settings.subsampling
        if self._budget is None:
            self._budget = (
                int(self._device.free_memory // gpu_share() * MEMORY_SHARE)
                if self._device.is_cuda
                else pass_bytes(w, h, CPU_BUDGET_WORLDS, jpeg, sub)
            )
        return max(self._budget, pass_bytes(w, h, self._largest_pass(settings), jpeg, sub))
