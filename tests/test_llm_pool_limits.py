"""Per-endpoint limits: the RPM/TPM limiter never exceeds its rates over any window, token
estimates are corrected after the call, concurrency is bounded (and adapts), retries jump the
queue. Windows are 1 s here instead of a minute: the code is the same, the test is short."""

from __future__ import annotations

import asyncio
import random

import pytest

from vabench.llm_pool import ChatRequest, LLMPool, RequestRejected, Turn
from vabench.llm_pool.limits import MIN_SLACK_S, ConcurrencyLimiter, RateBudget, RateLimiter
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.llm_pool.testing import max_in_window

REQUEST = ChatRequest([Turn.user("ping")])


def test_rate_limiter_never_exceeds_its_rates_over_any_window():
    rpm, tpm, period, burst_s = 30, 3000, 1.0, 0.1
    admitted: list[tuple[float, int]] = []  # (admission time, settled tokens)

    async def main():
        limiter = RateLimiter(rpm, tpm, period_s=period, burst_s=burst_s)
        loop = asyncio.get_running_loop()
        stop_at = loop.time() + 2.0
        rng = random.Random(7)

        async def caller():
            while loop.time() < stop_at:
                estimate = rng.randint(20, 400)
                admission = await limiter.acquire(estimate)
                await asyncio.sleep(rng.uniform(0.0, 0.05))  # the call
                actual = rng.randint(estimate // 4, estimate)  # usage known afterwards
                limiter.settle(admission, actual)
                admitted.append((admission.at, actual))

        await asyncio.gather(*(caller() for _ in range(20)))

    asyncio.run(main())
    requests = [(at, 1.0) for at, _ in admitted]
    assert len(admitted) >= rpm  # it admits (2 s of demand far above the limits)
    # A whole period, whichever period you pick.
    assert max_in_window(requests, period) <= rpm
    assert max_in_window([(at, float(t)) for at, t in admitted], period) <= tpm
    # Shorter windows: never more than the bucket plus the refill, i.e. smooth traffic.
    capacity = max(1.0, rpm / period * burst_s)
    for width in (0.05, 0.1, 0.3, 0.6):
        assert max_in_window(requests, width) <= capacity + rpm / period * width + 1e-9


def test_settling_corrects_the_token_window_both_ways():
    budget = RateBudget(100, period_s=10, burst_s=10)
    entry = budget.take(80, now=0.0)
    assert budget.wait_time(30, now=0.0) > 0  # 80 + 30 > 100
    budget.settle(entry, 50)  # the call used less: refund at once
    assert budget.wait_time(30, now=0.0) == 0
    budget.settle(entry, 120)  # it used more than estimated: charged when known
    wait = budget.wait_time(1, now=1.0)
    # until the entry leaves the window: 1 % longer than the period, at least MIN_SLACK_S
    assert wait == pytest.approx(max(10 * 1.01, 10 + MIN_SLACK_S) - 1.0)


def test_a_call_larger_than_the_token_limit_is_rejected_before_sending():
    async def main():
        async with LocalServer() as server:
            config = server.endpoint_config("m", "openai_chat", limits={"tpm": 1000})
            async with LLMPool([config]) as pool:
                with pytest.raises(RequestRejected) as err:
                    await pool.complete("m", REQUEST)  # 4,096 max output tokens alone
            return err.value, len(server.log)

    err, seen = asyncio.run(main())
    assert seen == 0 and err.attempts == 0 and "limits.tpm" in str(err)


def test_client_pacing_meets_a_server_enforcing_the_same_kind_of_limits():
    """The server enforces 20 requests and 4,000 tokens per 1 s window; the client is set 10 %
    under that, its burst scaled with the period (0.1 s of a 1 s period, as the default 1 s is
    of a minute). No request may be refused, and the server's log stays within its limits."""

    async def main():
        config = ServerConfig(rpm=20, tpm=4000, rate_period_s=1.0, latency={"mean_s": 0.05})
        async with LocalServer(config) as server:
            limits = {
                "rpm": 18,
                "tpm": 3600,
                "period_s": 1.0,
                "burst_s": 0.1,
                "max_concurrency": 20,
            }
            endpoint = server.endpoint_config(
                "m", "openai_chat", limits=limits, generation={"max_output_tokens": 100}
            )
            async with LLMPool([endpoint]) as pool:
                results = await asyncio.gather(*(pool.complete("m", REQUEST) for _ in range(50)))
            return results, list(server.log)

    results, log = asyncio.run(main())
    assert all(r.attempts == 1 for r in results)
    assert all(r.status == 200 for r in log)
    assert max_in_window([(r.received_s, 1.0) for r in log], 1.0) <= 20


def test_pool_never_has_more_than_max_concurrency_in_flight():
    async def main():
        async with LocalServer(ServerConfig(latency={"mean_s": 0.05})) as server:
            config = server.endpoint_config("m", "anthropic", limits={"max_concurrency": 4})
            async with LLMPool([config]) as pool:
                await asyncio.gather(*(pool.complete("m", REQUEST) for _ in range(40)))
            return list(server.log)

    log = asyncio.run(main())
    edges = sorted([(r.received_s, 1) for r in log] + [(r.finished_s, -1) for r in log])
    in_flight, peak = 0, 0
    for _, step in edges:
        in_flight += step
        peak = max(peak, in_flight)
    assert peak == 4


def test_retries_jump_the_queue_and_cancelled_waiters_leak_nothing():
    async def main():
        limiter = ConcurrencyLimiter(1)
        await limiter.acquire()
        order: list[str] = []

        async def wait(name: str, priority: bool = False):
            await limiter.acquire(priority=priority)
            order.append(name)
            limiter.release()

        tasks = [asyncio.create_task(wait("new-1")), asyncio.create_task(wait("new-2"))]
        await asyncio.sleep(0)
        doomed = asyncio.create_task(wait("cancelled"))
        tasks.append(asyncio.create_task(wait("retry", priority=True)))
        await asyncio.sleep(0)
        doomed.cancel()
        await asyncio.sleep(0)
        limiter.release()
        await asyncio.gather(*tasks)
        return order, limiter.in_flight, limiter.queued

    order, in_flight, queued = asyncio.run(main())
    assert order == ["retry", "new-1", "new-2"]
    assert in_flight == 0 and queued == 0


def test_adaptive_concurrency_halves_on_overload_and_grows_back():
    limiter = ConcurrencyLimiter(16, adaptive=True, floor=2)
    limiter.on_overload(now=0.0)
    assert limiter.bound == 8
    limiter.on_overload(now=0.5)  # same overload episode: no second cut
    assert limiter.bound == 8
    for now in (3.0, 6.0, 9.0, 12.0):
        limiter.on_overload(now)
    assert limiter.bound == 2  # the floor
    for _ in range(1000):
        limiter.on_success()
    assert limiter.bound == 16  # back to the ceiling, not beyond
    fixed = ConcurrencyLimiter(16)
    fixed.on_overload(now=0.0)
    assert fixed.bound == 16


def test_adaptive_endpoint_shrinks_after_a_429():
    async def main():
        async with LocalServer(ServerConfig(faults={"retry_after_s": 0.05})) as server:
            server.faults.script("rate_limit")
            limits = {"max_concurrency": 8, "adaptive": True}
            config = server.endpoint_config("m", "openai_chat", limits=limits)
            async with LLMPool([config]) as pool:
                await pool.complete("m", REQUEST)
                return pool.stats()["m"]

    stats = asyncio.run(main())
    assert stats.rate_limited == 1 and stats.concurrency_limit == 4


def test_a_waiter_cancelled_just_before_a_release_leaks_nothing():
    """cancel() and release() in the same loop turn: the release skips the cancelled waiter,
    which must then leave quietly (no error, no slot lost)."""

    async def main():
        limiter = ConcurrencyLimiter(1)
        await limiter.acquire()
        waiter = asyncio.create_task(limiter.acquire())
        await asyncio.sleep(0)  # queued
        waiter.cancel()
        limiter.release()  # before the waiter task runs again
        results = await asyncio.gather(waiter, return_exceptions=True)
        await asyncio.wait_for(limiter.acquire(), 1)  # the slot is free again
        return results, limiter.in_flight, limiter.queued

    results, in_flight, queued = asyncio.run(main())
    assert isinstance(results[0], asyncio.CancelledError)
    assert in_flight == 1 and queued == 0
