"""The rendering worker: processes that turn batch states plus camera poses into JPEG images.

Rendering and JPEG encoding are the second cost of every step after physics, and OpenGL wants
one context per thread, so images are made in separate processes, each with its own off-screen
context (EGL on the GPU, Mesa's llvmpipe without one; see `gl`). A `RenderPool` splits each
request over its workers in contiguous chunks and gathers the answers in order.

Failure handling: a worker that dies, stops answering within `timeout_s`, or fails inside
OpenGL is killed, started again, and its chunk is sent again, up to `max_attempts` times per
request; only then does the request fail with `RenderError`. A request that is wrong in itself
(unknown task, bad qpos shape or variant, size over the buffer) fails at once with the
worker's message, since sending it again cannot help. No observation is lost silently: the
caller gets every image of a request, in order, or an exception.

Processes are spawned, not forked: a fork would copy the parent's JAX runtime and GL state,
and the platform must be chosen before MuJoCo is first imported in the process.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing as mp
import os
import threading
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from vabench.children import children_ignore_sigint, ignore_sigint
from vabench.render import gl
from vabench.render.debug import DebugOverlays
from vabench.render.images import ImageSettings, RenderError, RenderItem, RenderStats

__all__ = ["ImageSettings", "RenderError", "RenderItem", "RenderPool", "RenderStats"]

log = logging.getLogger(__name__)


# -- the worker process ------------------------------------------------------------------------
class _RequestError(Exception):
    """Raised in the worker for a request that is wrong in itself (not retried)."""


def _send(conn: Connection, message: tuple[Any, ...]) -> bool:
    """Answer the pool; False when it is gone (its process ended): this worker ends quietly."""
    try:
        conn.send(message)
    except (BrokenPipeError, ConnectionResetError, EOFError):
        return False
    return True


def _worker_main(conn: Connection, platform: str, max_size: tuple[int, int]) -> None:
    ignore_sigint()  # the parent ends this process (vabench.children)
    gl.configure(platform)
    os.environ.setdefault("JAX_PLATFORMS", "cpu")  # task modules import JAX; keep it off GPUs
    try:
        from vabench.render.images import encode_jpeg
        from vabench.render.renderer import SceneRenderer
        from vabench.tasks import REGISTRY

        probe = gl.make_context(platform, 16, 16)
        info = gl.describe(platform)
        probe.free()
    except Exception as err:  # no GL here: say so and let the pool try another platform
        _send(conn, ("failed", f"{type(err).__name__}: {err}"))
        return
    if not _send(conn, ("ready", info)):
        return
    renderers: dict[str, SceneRenderer] = {}
    crash_next = False
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        kind = msg[0]
        if kind == "close":
            for r in renderers.values():
                r.close()
            return
        if kind == "crash_next":  # test hook: die on the next render request, before replying
            crash_next = True
            continue
        _, task_name, settings, items, overlays = msg
        if crash_next:
            os._exit(3)
        try:
            if task_name not in REGISTRY:
                raise _RequestError(f"unknown task {task_name!r}")
            if task_name not in renderers:
                renderers[task_name] = SceneRenderer(REGISTRY[task_name], platform, *max_size)
            renderer = renderers[task_name]
            images, t_render, t_encode = [], 0.0, 0.0
            for item in items:
                t0 = time.perf_counter()
                args = (item.qpos, item.variant, item.camera, settings.width, settings.height)
                try:
                    if overlays is None:
                        rgb = renderer.render(*args)
                    else:
                        rgb = renderer.render_debug(*args, overlays)
                except ValueError as err:
                    raise _RequestError(str(err)) from None
                t1 = time.perf_counter()
                images.append(encode_jpeg(rgb, settings.quality, settings.subsampling))
                t_render += t1 - t0
                t_encode += time.perf_counter() - t1
            reply: tuple[Any, ...] = ("ok", images, t_render, t_encode)
        except _RequestError as err:
            reply = ("bad_request", str(err))
        except Exception:  # a GL or driver failure: the pool restarts this worker
            _send(conn, ("crashed", traceback.format_exc()))
            return
        if not _send(conn, reply):
            return


# -- the pool ----------------------------------------------------------------------------------
@dataclass
class _Worker:
    process: Any
    conn: Connection
    index: int
    info: gl.GLInfo | None = None


@dataclass
class RenderPool:
    """Worker processes that render for every episode of a run.

    `platform` is "auto" (EGL, then OSMesa), "egl" or "osmesa". `egl_devices` spreads workers
    over GPUs (worker i uses `egl_devices[i % len]`). Use as a context manager or call
    `start()`/`close()`; the engine owns one pool.
    """

    workers: int = 1
    platform: str = "auto"
    max_size: tuple[int, int] = (1280, 960)
    timeout_s: float = 120.0
    max_attempts: int = 3
    egl_devices: Sequence[int] | None = None
    stats: RenderStats = field(default_factory=RenderStats)

    def __post_init__(self) -> None:
        if self.platform not in gl.PLATFORMS:
            raise ValueError(f"platform must be one of {gl.PLATFORMS}, got {self.platform!r}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        self._ctx = mp.get_context("spawn")
        self._pool: list[_Worker] = []
        self._lock = threading.Lock()
        self.resolved: str | None = None
        self.gl_info: gl.GLInfo | None = None

    # -- life cycle ----------------------------------------------------------------------
    def __enter__(self) -> RenderPool:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def start(self) -> gl.GLInfo:
        if self._pool:
            assert self.gl_info is not None
            return self.gl_info
        candidates = ("egl", "osmesa") if self.platform == "auto" else (self.platform,)
        reasons = []
        for platform in candidates:
            try:
                first = self._spawn(0, platform)
            except RenderError as err:
                reasons.append(f"{platform}: {err}")
                continue
            self.resolved, self.gl_info = platform, first.info
            self._pool = [first] + [self._spawn(i, platform) for i in range(1, self.workers)]
            log.debug("render workers: %d x %s", self.workers, self.gl_info)
            return first.info  # type: ignore[return-value]
        raise RenderError("no off-screen OpenGL platform works here: " + "; ".join(reasons))

    def _spawn(self, index: int, platform: str) -> _Worker:
        parent, child = self._ctx.Pipe()
        env_backup = os.environ.get("MUJOCO_EGL_DEVICE_ID")
        if self.egl_devices:
            device = self.egl_devices[index % len(self.egl_devices)]
            os.environ["MUJOCO_EGL_DEVICE_ID"] = str(device)
        try:
            proc = self._ctx.Process(
                target=_worker_main,
                args=(child, platform, self.max_size),
                name=f"vabench-render-{index}",
                daemon=True,
            )
            with children_ignore_sigint():
                proc.start()
        finally:
            if self.egl_devices:
                if env_backup is None:
                    os.environ.pop("MUJOCO_EGL_DEVICE_ID", None)
                else:
                    os.environ["MUJOCO_EGL_DEVICE_ID"] = env_backup
        child.close()
        worker = _Worker(proc, parent, index)
        if not parent.poll(self.timeout_s):
            self._kill(worker)
            raise RenderError(f"worker did not start within {self.timeout_s:.0f} s")
        try:
            status, payload = parent.recv()
        except (EOFError, OSError):
            self._kill(worker)
            raise RenderError(f"worker exited at start (code {proc.exitcode})") from None
        if status != "ready":
            self._kill(worker)
            raise RenderError(str(payload))
        worker.info = payload
        return worker

    def _kill(self, worker: _Worker) -> None:
        if worker.process.is_alive():
            worker.process.kill()
        worker.process.join(timeout=10)
        worker.conn.close()

    def _restart(self, worker: _Worker) -> _Worker:
        self._kill(worker)
        assert self.resolved is not None
        fresh = self._spawn(worker.index, self.resolved)
        self._pool[worker.index] = fresh
        self.stats.restarts += 1
        log.warning("render worker %d restarted", worker.index)
        return fresh

    def close(self) -> None:
        for worker in self._pool:
            with contextlib.suppress(OSError, ValueError):
                worker.conn.send(("close",))
        for worker in self._pool:
            worker.process.join(timeout=5)
            self._kill(worker)
        self._pool = []

    @property
    def pids(self) -> list[int]:
        return [w.process.pid for w in self._pool]

    def crash_next(self, index: int) -> None:
        """Test hook: worker `index` dies on its next request, before answering."""
        self._pool[index].conn.send(("crash_next",))

    # -- requests --------------------------------------------------------------------------
    def render(
        self,
        task: str,
        items: Sequence[RenderItem],
        settings: ImageSettings | None = None,
        source: Any = None,
    ) -> list[bytes]:
        """The model images: JPEG bytes for every item, in order (blocking; thread-safe).
        `source` is ignored: GL workers draw the items' host states."""
        return self._request(task, items, settings or ImageSettings(), None)

    def render_debug(
        self,
        task: str,
        items: Sequence[RenderItem],
        overlays: DebugOverlays,
        settings: ImageSettings | None = None,
    ) -> list[bytes]:
        """Images for people, with `overlays`; never send these to a model."""
        if not isinstance(overlays, DebugOverlays):
            raise TypeError(f"overlays must be DebugOverlays, got {type(overlays).__name__}")
        return self._request(task, items, settings or ImageSettings(), overlays)

    def _request(
        self,
        task: str,
        items: Sequence[RenderItem],
        settings: ImageSettings,
        overlays: DebugOverlays | None,
    ) -> list[bytes]:
        if settings.width > self.max_size[0] or settings.height > self.max_size[1]:
            raise RenderError(
                f"image size {settings.width}x{settings.height} exceeds the pool's buffer "
                f"{self.max_size[0]}x{self.max_size[1]}"
            )
        items = list(items)
        if not items:
            return []
        with self._lock:
            if not self._pool:
                raise RenderError("the render pool is not started")
            t0 = time.perf_counter()
            n = min(len(self._pool), len(items))
            bounds = np.linspace(0, len(items), n + 1).astype(int)
            chunks = [items[bounds[i] : bounds[i + 1]] for i in range(n)]
            out: list[list[bytes] | None] = [None] * n
            attempts = [0] * n
            pending = list(range(n))
            while pending:
                for i in pending:
                    attempts[i] += 1
                    self._send(i, ("render", task, settings, chunks[i], overlays))
                # Read every answer before raising, so no reply is left behind in a pipe.
                results = {i: self._collect(i, out) for i in pending}
                bad = [r for r in results.values() if isinstance(r, str)]
                if bad:
                    raise RenderError(bad[0])
                failed = [i for i, ok in results.items() if ok is False]
                for i in failed:
                    if attempts[i] >= self.max_attempts:
                        raise RenderError(
                            f"render worker {i} failed {attempts[i]} times on one request"
                        )
                    self.stats.retries += 1
                pending = failed
            self.stats.requests += 1
            self.stats.images += len(items)
            self.stats.wall_s += time.perf_counter() - t0
            return [img for chunk in out for img in chunk or []]

    async def render_async(
        self, task: str, items: Sequence[RenderItem], settings: ImageSettings | None = None
    ) -> list[bytes]:
        """`render` off the event loop."""
        return await asyncio.to_thread(self.render, task, items, settings)

    def _send(self, i: int, msg: tuple) -> None:
        worker = self._pool[i]
        if not worker.process.is_alive():
            worker = self._restart(worker)
        try:
            worker.conn.send(msg)
        except (OSError, ValueError):  # died between the check and the send
            self._restart(worker).conn.send(msg)

    def _collect(self, i: int, out: list[list[bytes] | None]) -> bool | str:
        """Read worker i's answer into out[i]: True; False (worker restarted) after a crash;
        the worker's message for a request that is wrong in itself."""
        worker = self._pool[i]
        try:
            if not worker.conn.poll(self.timeout_s):
                log.warning("render worker %d timed out after %.0f s", i, self.timeout_s)
                self._restart(worker)
                return False
            reply = worker.conn.recv()
        except (EOFError, OSError):
            self._restart(worker)
            return False
        status = reply[0]
        if status == "ok":
            out[i] = reply[1]
            self.stats.render_s += reply[2]
            self.stats.encode_s += reply[3]
            return True
        if status == "bad_request":
            return str(reply[1])
        log.warning("render worker %d failed:\n%s", i, reply[1])
        self._restart(worker)
        return False
