"""2,000 calls at concurrency 200 against a server injecting every kind of fault in 20 % of its
responses: every call ends exactly once, with a result or a typed infrastructure error; no
result belongs to another call; usage is counted once; no connection outlives the pool."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re

from vabench.llm_pool import ChatRequest, CompletionResult, InfrastructureError, LLMPool, Turn
from vabench.llm_pool.apis import IncomingRequest
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.llm_pool.testing import synthetic_image

CALLS = 2000
CONCURRENCY = 200
FAULTS = {  # 20 % in all, every kind
    "rate_limit": 0.03,
    "overloaded": 0.02,
    "unavailable": 0.02,
    "server_error": 0.03,
    "slow": 0.02,
    "malformed": 0.03,
    "truncated": 0.03,
    "drop": 0.02,
}


class Echo:
    """Replies with the call's id and remembers how often each id was answered."""

    def __init__(self):
        self.answered: dict[int, int] = {}

    async def respond(self, request: IncomingRequest) -> str:
        call = int(re.search(r"call (\d+)", request.chat.last_user_text).group(1))
        self.answered[call] = self.answered.get(call, 0) + 1
        return f"answer to call {call}"


def _sockets() -> int:
    fd_dir = "/proc/self/fd"
    count = 0
    for fd in os.listdir(fd_dir):
        with contextlib.suppress(OSError):
            count += os.readlink(f"{fd_dir}/{fd}").startswith("socket:")
    return count


def test_2000_calls_with_20_percent_faults_end_exactly_once():
    echo = Echo()
    image = synthetic_image(320, 240, size=2_000)

    async def main():
        config = ServerConfig(
            latency={"mean_s": 0.02, "dist": "uniform", "spread": 0.5},
            faults={"rates": FAULTS, "retry_after_s": 0.05, "slow_s": 6.0},
            seed=11,
        )
        async with LocalServer(config, policy=echo) as server:
            sockets_before = _sockets()
            endpoint = server.endpoint_config(
                "m",
                "openai_chat",
                limits={"max_concurrency": CONCURRENCY},
                retry={
                    "max_attempts": 4,
                    # A loaded machine's event loop is late by seconds: a 0.02 s reply must
                    # not time out, nor the 2,000 calls reach a deadline; only the injected
                    # slow replies (6 s) time out.
                    "request_timeout_s": 3.0,
                    "total_timeout_s": 300.0,
                    "backoff_base_s": 0.02,
                    "backoff_max_s": 0.2,
                },
            )
            pool = LLMPool([endpoint], seed=3)
            requests = [ChatRequest([Turn.user(f"call {i}", image)]) for i in range(CALLS)]
            outcomes = await asyncio.gather(
                *(pool.complete("m", r) for r in requests), return_exceptions=True
            )
            stats = pool.stats()["m"]
            await pool.close()
            for _ in range(200):
                if server.open_connections == 0:
                    break
                await asyncio.sleep(0.01)
            return outcomes, stats, server.open_connections, sockets_before, _sockets(), server

    outcomes, stats, still_open, sockets_before, sockets_after, server = asyncio.run(main())

    assert len(outcomes) == CALLS
    kinds = {type(o) for o in outcomes}
    assert kinds <= {CompletionResult, InfrastructureError}, kinds
    results = [(i, o) for i, o in enumerate(outcomes) if isinstance(o, CompletionResult)]
    failures = [o for o in outcomes if isinstance(o, InfrastructureError)]
    # Every result answers its own call.
    assert all(r.text == f"answer to call {i}" for i, r in results)
    # 4 attempts at 20 % faults: about 0.2**4 * 2000 = 3 calls fail; allow a wide margin.
    assert len(results) >= CALLS - 30
    # 429/529 answers are waits, not failures (`pool._Call.rate_waits`): a call gives up after
    # 4 attempts besides them, or at its deadline
    waits = re.compile(r"HTTP (?:429|529)\b")
    assert all(
        len([x for x in f.failures if not waits.match(x)]) == 4 or "deadline" in str(f)
        for f in failures
    )
    assert all(f.attempts == len(f.failures) for f in failures)
    # The pool's books agree with the outcomes: each call counted once, usage once.
    assert stats.started == CALLS and stats.succeeded == len(results)
    assert stats.failed == len(failures) and stats.rejected == stats.cancelled == 0
    assert stats.in_flight == 0 and stats.queued == 0
    total = results[0][1].usage
    for _, r in results[1:]:
        total = total + r.usage
    assert stats.usage == total
    assert stats.attempts == sum(r.attempts for _, r in results) + sum(f.attempts for f in failures)
    # Nothing lost, nothing twice: every answer the policy produced was delivered to exactly
    # one successful call, or destroyed on the way by an injected fault (malformed, truncated),
    # or arrived after the client's timeout (the injected slow replies never get that far:
    # the server cancels them when the client hangs up).
    assert all(echo.answered.get(i, 0) >= 1 for i, _ in results)
    lines = [line for _, r in results for line in r.failures]
    lines += [line for f in failures for line in f.failures]
    late = sum("timeout" in line for line in lines) - server.counts["fault:slow"]
    # Replies destroyed on the way: only those the policy wrote (a client that timed out while
    # such a request still waited for its latency never got a policy answer to destroy).
    destroyed = sum(
        1
        for record in server.log
        if record.fault in ("malformed", "truncated") and record.output_tokens > 0
    )
    extra = sum(echo.answered.values()) - len(results) - destroyed
    assert 0 <= extra <= late
    assert sum(server.counts[f"fault:{k}"] for k in FAULTS) > 0.1 * CALLS
    # No connection outlives the pool: none open on the server, no socket left in the client.
    assert still_open == 0
    assert sockets_after <= sockets_before
