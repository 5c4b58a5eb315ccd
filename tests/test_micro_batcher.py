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


def _gated_batcher(concurrency: int):
    """A batcher whose calls block until released one by one, recording each call's items and
    how many calls were inside `run` at once."""
    gates: list[threading.Event] = []
    calls: list[list[int]] = []
    inside = [0, 0]  # now, most
    lock = threading.Lock()

    def run(items):
        gate = threading.Event()
        with lock:
            gates.append(gate)
            calls.append(list(items))
            inside[0] += 1
            inside[1] = max(inside[1], inside[0])
        assert gate.wait(20), "never released"
        with lock:
            inside[0] -= 1
        return [x * 10 for x in items]

    batcher = MicroBatcher(run, window_s=0, name="gated", concurrency=concurrency)
    return batcher, gates, calls, inside


async def _until(predicate):
    for _ in range(2000):
        if predicate():
            return
        await asyncio.sleep(0.005)
    raise AssertionError("condition not reached")


def test_one_call_at_a_time_by_default_and_items_gather_meanwhile():
    async def main():
        b, gates, calls, inside = _gated_batcher(1)
        first = asyncio.ensure_future(b.submit(1))
        await _until(lambda: len(calls) == 1)
        later = [asyncio.ensure_future(b.submit(i)) for i in (2, 3, 4)]
        await asyncio.sleep(0.05)
        assert len(calls) == 1  # the others wait for the call in flight...
        gates[0].set()
        await _until(lambda: len(calls) == 2)
        assert calls[1] == [2, 3, 4]  # ...and go together in the next one
        gates[1].set()
        results = await asyncio.gather(first, *later)
        await b.close()
        return results, inside[1]

    results, most = asyncio.run(main())
    assert results == [10, 20, 30, 40] and most == 1


def test_with_concurrency_two_a_second_batch_starts_while_the_first_runs():
    """A renderer that serves requests side by side: one group's images need not wait for
    another group's whole call; a third batch gathers until a call ends."""

    async def main():
        b, gates, calls, inside = _gated_batcher(2)
        first = asyncio.ensure_future(b.submit(1))
        await _until(lambda: len(calls) == 1)
        second = asyncio.ensure_future(b.submit(2))
        await _until(lambda: len(calls) == 2)  # started while the first still runs
        later = [asyncio.ensure_future(b.submit(i)) for i in (3, 4)]
        await asyncio.sleep(0.05)
        assert len(calls) == 2  # both calls busy: the rest gather
        gates[1].set()  # the second call ends first: its result does not wait for the first
        assert await second == 20
        await _until(lambda: len(calls) == 3)
        assert calls[2] == [3, 4]
        gates[0].set()
        gates[2].set()
        results = await asyncio.gather(first, *later)
        await b.close()
        return results, inside[1], b.stats.calls

    results, most, n_calls = asyncio.run(main())
    assert results == [10, 30, 40] and most == 2 and n_calls == 3


def test_close_with_calls_in_flight_cancels_their_episodes_and_serves_again():
    async def main():
        b, gates, calls, _ = _gated_batcher(2)
        waiting = [asyncio.ensure_future(b.submit(i)) for i in (1, 2)]
        await _until(lambda: len(calls) >= 1)
        await b.close()
        for g in gates:
            g.set()
        outcomes = await asyncio.gather(*waiting, return_exceptions=True)
        again = asyncio.ensure_future(b.submit(5))
        await _until(lambda: len(gates) >= len(calls) and len(calls) >= 2)
        for g in list(gates):
            g.set()
        result = await again
        await b.close()
        return outcomes, result

    outcomes, result = asyncio.run(main())
    assert all(isinstance(o, asyncio.CancelledError) for o in outcomes)
    assert result == 50


def test_concurrency_below_one_is_refused():
    import pytest

    with pytest.raises(ValueError, match="concurrency must be >= 1"):
        MicroBatcher(lambda items: list(items), concurrency=0)


def test_a_render_service_sends_as_many_requests_at_once_as_its_pool_serves():
    from types import SimpleNamespace

    from vabench.agent.simulation import RenderService
    from vabench.render.images import ImageSettings

    side_by_side = RenderService(SimpleNamespace(concurrent_requests=2), "t", ImageSettings())
    one_at_a_time = RenderService(SimpleNamespace(), "t", ImageSettings())  # GL's pool
    assert side_by_side._batcher.concurrency == 2
    assert one_at_a_time._batcher.concurrency == 1


def test_a_task_batch_is_freed_by_reference_counting_when_its_task_ends():
    """The simulator and render services own their batchers, and each batcher runs one of its
    owner's methods: held strongly, that would make a cycle that only a full collection frees,
    keeping the task's physics batch (its GPU arrays, on a GPU) alive until then, while the
    sweep builds the next task's. With the collector off, the batch and its services must go
    as soon as the task's services are closed and dropped."""
    import gc
    import weakref

    from vabench.agent.services import task_services
    from vabench.tasks import get_task

    class Pool:  # a renderer that reads its states from the physics batch, as Warp's does
        def shares(self, batch):
            return True

    async def main():
        async with task_services(get_task("probe_cube"), 2, None, Pool(), backend="c") as svc:
            await svc.sim.reset(0, 0)  # the batcher's dispatch and thread exist, as in a sweep
            kept = (svc.sim, svc.sim.batch, svc.sim.batch.batch, svc.render)
            refs = [weakref.ref(o) for o in kept]
            del kept
        del svc
        return refs

    gc.collect()
    gc.disable()
    try:
        refs = asyncio.run(main())
        alive = [type(r()).__name__ for r in refs if r() is not None]
    finally:
        gc.enable()
    assert alive == []
