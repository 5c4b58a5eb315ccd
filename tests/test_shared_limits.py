"""Limits shared by several processes (`llm_pool.shared_limits.SharedLimits` against the board
of `llm_pool.limit_board`), here in one loop with the board reached through `LocalChannel`: what
crosses a process boundary in a Ray sweep is the same calls. The Ray version is
tests/test_ray_limiter.py. Windows are 1 s instead of a minute: the code is the same."""

from __future__ import annotations

import asyncio

from vabench.llm_pool import ChatRequest, LLMPool, Turn
from vabench.llm_pool.limit_board import BoardLimits, LimitBoard, LocalChannel
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.llm_pool.testing import max_in_window

REQUEST = ChatRequest([Turn.user("ping")])
# The client is set 10 % under what the server enforces, its burst scaled to the 1 s period,
# as in test_llm_pool_limits.py::test_client_pacing_meets_a_server_enforcing_...
LIMITS = {"rpm": 18, "tpm": 3600, "period_s": 1.0, "burst_s": 0.1, "max_concurrency": 20}
SERVER = ServerConfig(rpm=20, tpm=4000, rate_period_s=1.0, latency={"mean_s": 0.05})


async def four_pools(shared: bool, calls: int = 15) -> tuple[list, list, dict]:
    """Four pools (four processes of a sweep) each sending `calls` calls at once to one server
    that enforces its limits; returns (results, the server's log, the board's stats)."""
    async with LocalServer(SERVER) as server:
        endpoint = server.endpoint_config(
            "m",
            "openai_chat",
            limits=LIMITS,
            generation={"max_output_tokens": 100},
            retry={"max_attempts": 20, "backoff_base_s": 0.05, "backoff_max_s": 0.2},
        )
        board = LimitBoard({"m": LIMITS})
        channel = LocalChannel(board)
        boards = [BoardLimits(channel, f"actor-{i}", ["m"] if shared else []) for i in range(4)]
        pools = [LLMPool([endpoint], shared_limits=b) for b in boards]
        try:
            results = await asyncio.gather(
                *(pool.complete("m", REQUEST) for pool in pools for _ in range(calls))
            )
        finally:
            for pool, limits in zip(pools, boards, strict=True):
                await pool.close()
                await limits.close()
        return results, list(server.log), board.stats()


def test_four_pools_sharing_the_board_stay_within_the_servers_limits():
    results, log, stats = asyncio.run(four_pools(shared=True))
    assert len(results) == 60 and all(r.attempts == 1 for r in results)
    assert all(r.status == 200 for r in log) and len(log) == 60  # the server refused nothing
    assert max_in_window([(r.received_s, 1.0) for r in log], 1.0) <= 20
    assert stats["m"]["admitted"] == 60 and stats["m"]["in_flight"] == 0
    assert stats["m"]["held"] == {}


def test_four_pools_with_their_own_limits_exceed_the_servers():
    """The control: the same four pools, each keeping the endpoint's limits for itself, send
    four times the rate and the server refuses some (each is retried until it passes)."""
    results, log, _ = asyncio.run(four_pools(shared=False, calls=10))
    assert len(results) == 40
    assert sum(r.status == 429 for r in log) > 0


def test_a_retry_after_seen_by_one_process_holds_every_process():
    async def main() -> float:
        board = LimitBoard({"m": {"max_concurrency": 4}})
        channel = LocalChannel(board)
        a, b = BoardLimits(channel, "a", ["m"]), BoardLimits(channel, "b", ["m"])
        endpoint = _endpoint()
        seen_by_a, other = a(endpoint), b(endpoint)
        await other.rate.acquire(10)  # admitted at once before the pause
        loop = asyncio.get_running_loop()
        seen_by_a.pause(0.3)
        t0 = loop.time()
        await other.rate.acquire(10)
        return loop.time() - t0

    assert asyncio.run(main()) >= 0.29


def test_concurrency_is_bounded_across_processes_and_a_dead_holders_slots_come_back():
    async def main() -> tuple[int, int, dict]:
        board = LimitBoard({"m": {"max_concurrency": 3}})
        channel = LocalChannel(board)
        holders = [BoardLimits(channel, name, ["m"]) for name in ("a", "b")]
        slots = [h(_endpoint(3)).concurrency for h in holders]
        in_use, peak = 0, 0

        async def call(limiter, seconds: float) -> None:
            nonlocal in_use, peak
            async with limiter.slot():
                in_use += 1
                peak = max(peak, in_use)
                try:
                    await asyncio.sleep(seconds)
                finally:
                    in_use -= 1

        tasks = [call(s, 0.01 * (i % 3)) for s in slots for i in range(12)]
        doomed = asyncio.create_task(call(slots[0], 10))  # cancelled while it holds or waits
        await asyncio.sleep(0.02)
        doomed.cancel()
        await asyncio.gather(*tasks)
        await asyncio.gather(doomed, return_exceptions=True)
        await asyncio.sleep(0)  # the last reports
        after = board.stats()["m"]["in_flight"]

        # a process that dies holding slots: the driver forgets it and they come back
        dead = BoardLimits(channel, "dead", ["m"])(_endpoint(3)).concurrency
        for _ in range(3):
            await dead.acquire()
        late = BoardLimits(channel, "late", ["m"])(_endpoint(3)).concurrency
        waiting = asyncio.create_task(late.acquire())
        await asyncio.sleep(0.05)
        assert not waiting.done()
        board.forget("dead")
        await asyncio.wait_for(waiting, 60)  # a guard against hanging, not a bound
        return peak, after, board.stats()["m"]["held"]

    peak, after, held = asyncio.run(main())
    assert peak == 3 and after == 0
    assert held == {"late": 1}


def test_a_process_queued_behind_a_flood_is_served_in_turn():
    """Slots go back to the board, never from call to call inside a process: a process that
    asks while another has 30 calls queued gets the next free slot but one, not the 31st."""

    async def main() -> int:
        board = LimitBoard({"m": {"max_concurrency": 2}})
        channel = LocalChannel(board)
        busy = BoardLimits(channel, "busy", ["m"])(_endpoint(2)).concurrency
        quiet = BoardLimits(channel, "quiet", ["m"])(_endpoint(2)).concurrency
        served: list[str] = []

        async def call(limiter, name: str) -> None:
            async with limiter.slot():
                served.append(name)
                await asyncio.sleep(0.01)

        flood = [asyncio.create_task(call(busy, "busy")) for _ in range(30)]
        await asyncio.sleep(0.005)
        await call(quiet, "quiet")
        await asyncio.gather(*flood)
        return served.index("quiet")

    assert asyncio.run(main()) <= 6


def _endpoint(max_concurrency: int = 4):
    from vabench.llm_pool import load_endpoint

    return load_endpoint(
        {
            "name": "m",
            "api": "openai_chat",
            "base_url": "http://127.0.0.1:9",
            "limits": {"max_concurrency": max_concurrency},
        }
    )
