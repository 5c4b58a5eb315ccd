"""Micro-batching: requests from many episode coroutines, executed together off the event loop.

Each episode awaits `submit(item)`. The first item of a batch opens a short window
(`window_s`); when it closes, or as soon as `max_batch` items are waiting, everything waiting
goes to `run(items)` in one call on a worker thread, and each episode gets its own result.
Up to `concurrency` calls run at a time (1 by default: a simulator batch is a single resource;
a renderer that serves requests side by side may take more, so that one group's images do not
wait for another's whole call), on threads of the batcher's own: a sweep runs dozens of
batchers at once, and on asyncio's shared default pool (cores + 4 threads) their calls queued
for a thread, so that on a 16-core GPU host some tasks never started while others held every
thread (seen in a profile of the suite). Items that arrive meanwhile form the next batch,
so under load the window costs nothing: the next batch is already waiting when a call returns
(a batch is formed only when a call may start, so items keep gathering while every call is
busy).

A call that raises fails every item of its batch with the same exception: each episode
decides what that means for it (the engine records an infrastructure error).
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import time
import weakref
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")


@dataclass
class BatchStats:
    calls: int = 0
    items: int = 0
    busy_s: float = 0.0  # inside `run` (calls side by side each count)
    max_batch: int = 0

    @property
    def mean_batch(self) -> float:
        return self.items / self.calls if self.calls else 0.0


class MicroBatcher(Generic[T, R]):
    """Collects items for `run`, which returns one result per item, in order."""

    def __init__(
        self,
        run: Callable[[Sequence[T]], Sequence[R]],
        *,
        window_s: float = 0.01,
        max_batch: int | None = None,
        name: str = "batch",
        concurrency: int = 1,
    ):
        if concurrency < 1:
            raise ValueError(f"concurrency must be >= 1, got {concurrency}")
        if window_s < 0:
            raise ValueError(f"window_s must be >= 0, got {window_s}")
        if max_batch is not None and max_batch < 1:
            raise ValueError(f"max_batch must be >= 1, got {max_batch}")
        # A bound method is held weakly: its object owns this batcher (the simulator and render
        # services do), and a strong reference back would make a cycle, keeping the owner's
        # task batch (its GPU arrays, on a GPU) alive after its task until a full collection
        # (tests/test_micro_batcher.py).
        self._run: Callable[[], Callable[[Sequence[T]], Sequence[R]] | None] = (
            weakref.WeakMethod(run) if inspect.ismethod(run) else lambda: run
        )
        self.window_s = window_s
        self.max_batch = max_batch
        self.name = name
        self.concurrency = concurrency
        self.stats = BatchStats()
        self._pending: list[tuple[T, asyncio.Future[R]]] = []
        self._wake: asyncio.Event | None = None
        self._full: asyncio.Event | None = None
        self._task: asyncio.Task[None] | None = None
        self._thread: ThreadPoolExecutor | None = None
        self._slots: asyncio.Semaphore | None = None  # calls that may start now
        self._calls: set[asyncio.Task[None]] = set()  # calls in flight (concurrency > 1)

    async def submit(self, item: T) -> R:
        loop = asyncio.get_running_loop()
        if self._task is None or self._task.done():
            self._wake, self._full = asyncio.Event(), asyncio.Event()
            self._slots = asyncio.Semaphore(self.concurrency)
            self._task = loop.create_task(self._dispatch(), name=f"{self.name}-dispatch")
        assert self._wake is not None and self._full is not None
        future: asyncio.Future[R] = loop.create_future()
        self._pending.append((item, future))
        self._wake.set()
        if self.max_batch is not None and len(self._pending) >= self.max_batch:
            self._full.set()
        return await future

    async def _dispatch(self) -> None:
        assert self._wake is not None and self._full is not None and self._slots is not None
        while True:
            await self._wake.wait()
            await self._slots.acquire()  # a call may start: form its batch now
            if self.window_s > 0 and not self._full.is_set():
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self._full.wait(), self.window_s)
            take = len(self._pending) if self.max_batch is None else self.max_batch
            batch, self._pending = self._pending[:take], self._pending[take:]
            if not self._pending:
                self._wake.clear()
            self._full.clear()
            if self.max_batch is not None and len(self._pending) >= self.max_batch:
                self._full.set()
            live = [(item, fut) for item, fut in batch if not fut.cancelled()]
            if not live:
                self._slots.release()
                continue
            if self.concurrency == 1:
                await self._execute(live)
            else:
                call = asyncio.get_running_loop().create_task(self._execute(live))
                self._calls.add(call)
                call.add_done_callback(self._calls.discard)

    async def _execute(self, batch: list[tuple[T, asyncio.Future[R]]]) -> None:
        slots = self._slots  # this call's (close and a later submit make new ones)
        items = [item for item, _ in batch]
        t0 = time.perf_counter()
        try:
            if self._thread is None:
                self._thread = ThreadPoolExecutor(self.concurrency, thread_name_prefix=self.name)
            loop = asyncio.get_running_loop()
            results = await loop.run_in_executor(self._thread, self._target(), items)
            if len(results) != len(items):
                raise RuntimeError(
                    f"{self.name}: run returned {len(results)} results for {len(items)} items"
                )
        except Exception as err:  # every waiting episode learns of the failure
            for _, fut in batch:
                if not fut.done():
                    fut.set_exception(err)
            return
        except asyncio.CancelledError:  # closed with the call in flight: its episodes too
            for _, fut in batch:
                fut.cancel()
            raise
        finally:
            assert slots is not None
            slots.release()
            dt = time.perf_counter() - t0
            self.stats.calls += 1
            self.stats.items += len(items)
            self.stats.busy_s += dt
            self.stats.max_batch = max(self.stats.max_batch, len(items))
        for (_, fut), result in zip(batch, results, strict=True):
            if not fut.done():
                fut.set_result(result)

    def _target(self) -> Callable[[Sequence[T]], Sequence[R]]:
        run = self._run()
        if run is None:
            raise RuntimeError(f"{self.name}: the object whose method this batcher runs is gone")
        return run

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        for call in list(self._calls):  # their threads' calls finish on their own
            call.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await call
        for _, fut in self._pending:
            if not fut.done():
                fut.cancel()
        self._pending = []
        if self._thread is not None:
            self._thread.shutdown(wait=False)  # a call in flight finishes on its own
            self._thread = None
