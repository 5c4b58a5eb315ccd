"""The limit board of a Ray sweep (`llm_pool.limit_board.LimiterActor`): four actors, each with its
own LLM pool, against one embedded server that enforces its rate limit and counts what it gets.
Together they never exceed it (the server refuses nothing) and all finish; a Retry-After one
of them is told holds the others too. Windows are 1 s instead of a minute: the code is the
same. The same board in one process, with the control (four pools with limits of their own
exceed the server's): tests/test_shared_limits.py.
"""

from __future__ import annotations

import asyncio
import time

import pytest
import ray

from vabench.llm_pool.limit_board import LimiterActor
from vabench.llm_pool.testing import max_in_window

# The client is set 10 % under what the server enforces (as in test_llm_pool_limits.py).
LIMITS = {"rpm": 18, "tpm": 3600, "period_s": 1.0, "burst_s": 0.1, "max_concurrency": 20}
SERVER = {"rpm": 20, "tpm": 4000, "rate_period_s": 1.0, "latency": {"mean_s": 0.05}}


@pytest.fixture(scope="module")
def actors():
    """A local Ray instance with the server and caller actors (defined here, so that Ray ships
    them by value)."""
    try:
        ray.init(address="local", num_cpus=2, include_dashboard=False)
    except Exception as err:  # say why, never skip
        pytest.fail(f"a local Ray instance does not start here: {type(err).__name__}: {err}")

    @ray.remote(num_cpus=0)
    class Server:
        """The embedded server, enforcing `SERVER`'s limits; `log()`: (arrival, status) of
        every request."""

        async def start(self, config: dict, faults: list[str]) -> dict:
            from vabench.llm_pool.server import LocalServer, ServerConfig

            self.server = await LocalServer(ServerConfig(**config)).start()
            self.server.faults.script(*faults)
            return self.server.endpoint_config(
                "m",
                "openai_chat",
                limits=LIMITS,
                generation={"max_output_tokens": 100},
                retry={"max_attempts": 5, "backoff_base_s": 0.05, "backoff_max_s": 0.2},
            )

        async def log(self) -> list[tuple[float, int | None]]:
            return [(r.received_s, r.status) for r in self.server.log]

    @ray.remote(num_cpus=0)
    class Caller:
        """A process of the sweep: its own pool, the board's limits."""

        async def run(
            self, endpoint: dict, calls: int, holder: str, limiter, after_pause: bool = False
        ) -> list[int]:
            from vabench.llm_pool import ChatRequest, LLMPool, Turn
            from vabench.llm_pool.limit_board import BoardLimits, RayChannel

            while after_pause and (await limiter.stats.remote())["m"]["paused_s"] <= 0:
                await asyncio.sleep(0.01)  # until another actor's Retry-After paused the board
            limits = BoardLimits(RayChannel(limiter), holder, ["m"])
            request = ChatRequest([Turn.user("ping")])
            async with LLMPool([endpoint], shared_limits=limits) as pool:
                results = await asyncio.gather(*(pool.complete("m", request) for _ in range(calls)))
            await limits.close()
            return [r.attempts for r in results]

    yield Server, Caller
    ray.shutdown()


def board():
    return ray.remote(LimiterActor).options(num_cpus=0).remote({"m": LIMITS})


def test_four_actors_sharing_the_board_never_exceed_the_servers_limit(actors):
    Server, Caller = actors
    server = Server.remote()
    endpoint = ray.get(server.start.remote(SERVER, []))
    limiter = board()
    callers = [Caller.remote() for _ in range(4)]
    attempts = ray.get(
        [c.run.remote(endpoint, 15, f"actor-{i}", limiter) for i, c in enumerate(callers)]
    )
    log = ray.get(server.log.remote())
    assert [len(a) for a in attempts] == [15] * 4  # all finish
    assert all(n == 1 for a in attempts for n in a)
    assert len(log) == 60 and all(status == 200 for _, status in log)  # nothing refused
    assert max_in_window([(at, 1.0) for at, _ in log], 1.0) <= 20
    # A caller's last report is sent one-way as it closes, and Ray orders calls per caller
    # only: this process's stats call may be served first, so read until the reports are in.
    for _ in range(200):
        stats = ray.get(limiter.stats.remote())["m"]
        if stats["in_flight"] == 0:
            break
        time.sleep(0.05)
    assert stats["admitted"] == 60 and stats["in_flight"] == 0 and stats["held"] == {}


def test_a_retry_after_seen_by_one_actor_holds_the_others(actors):
    """The server answers the first request with a 429 and Retry-After: 1 s. The actor that
    gets it pauses the board; another actor, whose call comes once the board is paused, waits
    it out (however the two actors' starts fall on a loaded machine)."""
    Server, Caller = actors
    server = Server.remote()
    config = SERVER | {"faults": {"retry_after_s": 1.0}}
    endpoint = ray.get(server.start.remote(config, ["rate_limit"]))
    limiter = board()
    first, second = Caller.remote(), Caller.remote()
    attempts = ray.get(
        [
            first.run.remote(endpoint, 1, "first", limiter),
            second.run.remote(endpoint, 1, "second", limiter, True),
        ]
    )
    log = sorted(ray.get(server.log.remote()))
    assert attempts == [[2], [1]]
    (refused_at, refused), *later = log
    assert refused == 429 and len(later) == 2 and all(s == 200 for _, s in later)
    assert min(at for at, _ in later) - refused_at >= 0.95
