"""Memory per call: thousands of calls through the real pool and the real embedded server (20 %
faults of every kind) leave nothing behind once warm (issue 36's soak).

Three figures per call, measured between two points after a warm-up, each taken once the calls
in flight have ended (new ones wait):

- Python blocks (`sys.getallocatedblocks`): an object kept per call (a list of ids, a dict of
  stats, a task or traceback kept alive) is at least one block per call. pydantic-core keeps
  the short strings it parses from JSON (<= 64 characters) in a table of 16,384 (about 1 MB at
  most), bounded by design: the test fills it first, else each call's unique text adds ~2
  blocks until it is full;
- the C heap's bytes in use (glibc `mallinfo2`): a C-level allocation kept per call;
- the C heap's bytes taken from the system: what the 2026-11-25 soak saw grow (~200 bytes per
  call, RSS +1.9 MB/min) with nothing in use growing: asyncio's 256 KiB read buffers carved
  from a fragmenting heap (`llm_pool.heap`). It takes whole 128-256 KiB steps, so the bound
  allows one such step in the window, not one per few thousand calls.
"""

from __future__ import annotations

import asyncio
import ctypes
import gc
import itertools
import json
import sys

import pydantic_core
import pytest

from vabench.llm_pool import ChatRequest, InfrastructureError, LLMPool, Turn
from vabench.llm_pool.apis import ADAPTERS
from vabench.llm_pool.faults import FAULT_KINDS
from vabench.llm_pool.server import LocalServer, ServerConfig

WARM_UP = 2_000
MEASURED = 5_000
IN_FLIGHT = 100
MAX_BLOCKS_PER_CALL = 0.2  # a leaked object per call is >= 1; idle connections vary ~+-0.05
MAX_IN_USE_PER_CALL = 16  # bytes; a leaked C allocation per call is at least 32
MAX_HEAP_PER_CALL = 64  # bytes; 0-28 here, one 128-256 KiB step; ~190 on the old code


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            *("arena", "ordblks", "smblks", "hblks", "hblkhd"),
            *("usmblks", "fsmblks", "uordblks", "fordblks", "keepcost"),
        )
    ]


def _mallinfo2():
    try:
        fn = ctypes.CDLL(None).mallinfo2
    except (OSError, AttributeError):
        return None
    fn.restype = _MallInfo2
    return fn


MALLINFO2 = _mallinfo2()


def _sample() -> dict[str, int]:
    gc.collect()
    heap = MALLINFO2()
    return {"blocks": sys.getallocatedblocks(), "in_use": heap.uordblks, "heap": heap.arena}


@pytest.mark.skipif(MALLINFO2 is None, reason="glibc's mallinfo2 (glibc >= 2.33) is needed")
def test_calls_leave_no_memory_behind_once_warm():
    for start in range(0, 200_000, 1_000):  # ~12 times the table: every slot taken
        fill = [f"fill {i}" for i in range(start, start + 1_000)]  # (small: no heap headroom)
        pydantic_core.from_json(json.dumps(fill).encode(), cache_strings=True)

    async def main():
        timeout = 1.0
        config = ServerConfig(
            policy="echo",
            latency={"mean_s": 0.02, "dist": "lognormal", "spread": 0.5},
            faults={
                "rates": dict.fromkeys(FAULT_KINDS, 0.2 / len(FAULT_KINDS)),
                "retry_after_s": 0.01,
                "slow_s": timeout + 0.3,
            },
            simulate_cache=False,
            log_size=0,
            seed=3,
        )
        retry = {"request_timeout_s": timeout, "backoff_base_s": 0.01, "backoff_max_s": 0.05}
        apis = tuple(ADAPTERS)
        started = ended = wrong = 0
        samples: list[dict[str, int]] = []
        running = asyncio.Event()  # cleared: no new call starts (a sample is due)
        running.set()
        ids = itertools.count()
        async with LocalServer(config) as server:
            endpoints = [
                server.endpoint_config(api, api, retry=retry, limits={"max_concurrency": IN_FLIGHT})
                for api in apis
            ]
            async with LLMPool(endpoints, seed=3) as pool:

                async def caller(api: str) -> None:
                    nonlocal started, ended, wrong
                    while len(samples) < 2:
                        await running.wait()
                        call = next(ids)
                        started += 1
                        request = ChatRequest((Turn.user(f"call {call}"),))
                        try:
                            result = await pool.complete(api, request)
                            wrong += not result.text.startswith(f"call {call} ")
                        except InfrastructureError:
                            pass
                        ended += 1
                        if ended in (WARM_UP, WARM_UP + MEASURED):
                            running.clear()

                async def sampler() -> None:
                    """Each sample once every call has ended: what calls in flight hold
                    (a few thousand blocks) is not mistaken for growth."""
                    while len(samples) < 2:
                        await asyncio.sleep(0.01)
                        if not running.is_set() and started == ended:
                            samples.append(_sample())
                            running.set()

                await asyncio.gather(
                    sampler(), *(caller(apis[i % len(apis)]) for i in range(IN_FLIGHT))
                )
        return samples, wrong

    (before, after), wrong = asyncio.run(main())
    assert wrong == 0
    per_call = {k: (after[k] - before[k]) / MEASURED for k in before}
    assert per_call["blocks"] < MAX_BLOCKS_PER_CALL, per_call
    assert per_call["in_use"] < MAX_IN_USE_PER_CALL, per_call
    assert per_call["heap"] < MAX_HEAP_PER_CALL, per_call
