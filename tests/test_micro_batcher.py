"""MicroBatcher: many batchers block at once, each on a thread of its own.

A sweep on a GPU host runs a simulator and a renderer batcher per task (44 for
configs/all.yaml); their calls block on the device. On asyncio's shared default pool (cores + 4
threads) the calls of some batchers waited for a thread while others held every one, and on an
H100 whole tasks never started (2026-11-26).
"""

from __future__ import annotations

import asyncio
import threading

from vabench.agent.batching import MicroBatcher

BATCHERS = 40  # more than the default pool's threads on any machine with < 36 cores


def test_every_batcher_runs_on_its_own_thread_at_once():
    """Each batcher's call waits on a barrier that only opens when all of them are inside
    their call at the same time: with a shared pool smaller than the batcher count it never
    opens (BrokenBarrierError after the timeout)."""
    barrier = threading.Barrier(BATCHERS, timeout=20)
    names: set[str] = set()

    def run(items):
        names.add(threading.current_thread().name)
        barrier.wait()
        return [x * 2 for x in items]

    async def main():
        batchers = [MicroBatcher(run, window_s=0, name=f"b{i}") for i in range(BATCHERS)]
        try:
            return await asyncio.gather(*(b.submit(i) for i, b in enumerate(batchers)))
        finally:
            for b in batchers:
                await b.close()

    assert asyncio.run(main()) == [2 * i for i in range(BATCHERS)]
    assert len(names) == BATCHERS
    assert all(any(n.startswith(f"b{i}_") for n in names) for i in range(BATCHERS))


def test_a_closed_batcher_serves_again():
    """close() releases the batcher's thread; a later submit gets a new one."""

    async def main():
        b = MicroBatcher(lambda items: list(items), window_s=0, name="again")
        first = await b.submit(1)
        await b.close()
        second = await b.submit(2)
        await b.close()
        return first, second

    assert asyncio.run(main()) == (1, 2)
