"""Helpers for tests and benchmarks of the pool: images that look like JPEGs to every header
reader (start-of-image and start-of-frame markers with the given size) without being decoded,
so their size and byte count can be chosen freely and generated in microseconds; and the
busiest-window measure that rate-limit checks use; and a real server run in a thread
(`server_in_thread`), for an endpoint a sweep calls without starting it."""

from __future__ import annotations

import asyncio
import contextlib
import random
import threading
from collections.abc import Iterator
from typing import Any

from vabench.llm_pool.messages import Image


def synthetic_jpeg(width: int = 1280, height: int = 960, size: int = 4096, seed: int = 0) -> bytes:
    """`size` bytes starting with a JPEG header that declares width x height."""
    app0 = b"\xff\xe0\x00\x10JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00"
    sof0 = (
        b"\xff\xc0\x00\x11\x08"
        + height.to_bytes(2, "big")
        + width.to_bytes(2, "big")
        + b"\x03\x01\x22\x00\x02\x11\x01\x03\x11\x01"
    )
    head = b"\xff\xd8" + app0 + sof0
    filler = random.Random(seed).randbytes(max(0, size - len(head) - 2))
    return head + filler + b"\xff\xd9"


def synthetic_image(width: int = 1280, height: int = 960, size: int = 4096, seed: int = 0) -> Image:
    return Image(synthetic_jpeg(width, height, size, seed))


def max_in_window(events: list[tuple[float, float]], width: float) -> float:
    """The largest sum of amounts over half-open windows (t - width, t] of event times t
    (a window's sum only grows at an event, so these are all the windows there are)."""
    events = sorted(events)
    best, total, start = 0.0, 0.0, 0
    for at, amount in events:
        total += amount
        while events[start][0] <= at - width:
            total -= events[start][1]
            start += 1
        best = max(best, total)
    return best


@contextlib.contextmanager
def server_in_thread(config: Any) -> Iterator[Any]:
    """A real `LocalServer` of `config` (a `ServerConfig`) on loopback, run in a thread of its
    own for the block: an endpoint a sweep calls without starting it (what a provider or a
    local vLLM is to the sweep). Yields the started server (`base_url(api)`)."""
    from vabench.llm_pool.server import LocalServer

    ready = threading.Event()
    holder: dict[str, Any] = {}

    async def serve() -> None:
        async with LocalServer(config) as server:
            holder["server"], holder["stop"] = server, asyncio.Event()
            holder["loop"] = asyncio.get_running_loop()
            ready.set()
            await holder["stop"].wait()

    thread = threading.Thread(target=asyncio.run, args=(serve(),), daemon=True)
    thread.start()
    if not ready.wait(30):
        raise RuntimeError("the server did not start within 30 s")
    try:
        yield holder["server"]
    finally:
        holder["loop"].call_soon_threadsafe(holder["stop"].set)
        thread.join(30)
