"""Retries against the embedded server: Retry-After honoured, attempt ceiling and total deadline
respected, non-retryable 4xx failing at once, transport faults retried, malformed bodies named,
cancellation leaving no connection behind; and the header parsing behind the waits."""

from __future__ import annotations

import asyncio
import random
from datetime import datetime, timedelta, timezone
from email.utils import format_datetime

import pytest
from multidict import CIMultiDict

from vabench.llm_pool import ChatRequest, InfrastructureError, LLMPool, RequestRejected, Turn
from vabench.llm_pool.config import RetryPolicy
from vabench.llm_pool.policies import ScriptedPolicy
from vabench.llm_pool.retry import backoff_delay, decide, parse_go_duration, server_retry_after
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.llm_pool.transport import Transport

FAST_RETRY = {"backoff_base_s": 0.01, "backoff_max_s": 0.05}
REQUEST = ChatRequest([Turn.user("ping")])


async def _one_call(server, api="openai_chat", retry=None, **endpoint):
    config = server.endpoint_config("m", api, retry={**FAST_RETRY, **(retry or {})}, **endpoint)
    async with LLMPool([config]) as pool:
        return await pool.complete("m", REQUEST)


def test_retry_after_2_is_waited_out_before_the_retry():
    async def main():
        async with LocalServer(ServerConfig(faults={"retry_after_s": 2})) as server:
            server.faults.script("rate_limit", None)
            result = await _one_call(server)
            return result, list(server.log)

    result, log = asyncio.run(main())
    assert result.attempts == 2 and "HTTP 429" in result.failures[0]
    assert [r.status for r in log] == [429, 200]
    # The server's own clock: the retry arrived no sooner than the 2 s it asked for.
    assert log[1].received_s - log[0].received_s >= 2.0


@pytest.mark.parametrize("api", ["openai_chat", "anthropic"])
def test_attempt_ceiling(api):
    async def main():
        config = ServerConfig(faults={"rates": {"server_error": 1.0}})
        async with LocalServer(config) as server:
            with pytest.raises(InfrastructureError) as err:
                await _one_call(server, api, retry={"max_attempts": 3})
            return err.value, list(server.log)

    err, log = asyncio.run(main())
    assert err.attempts == 3 and len(log) == 3 and len(err.failures) == 3
    assert "gave up after 3 attempts" in str(err) and "HTTP 500" in str(err)


def test_total_deadline_bounds_slow_attempts(monkeypatch):
    retry = {"max_attempts": 100, "total_timeout_s": 1.0, "request_timeout_s": 0.3}
    timeouts: list[float] = []  # each attempt's timeout, as the pool hands it to the transport
    post = Transport.post

    async def counted_post(self, body, timeout):
        timeouts.append(timeout)
        return await post(self, body, timeout)

    monkeypatch.setattr(Transport, "post", counted_post)

    async def main():
        config = ServerConfig(faults={"rates": {"slow": 1.0}, "slow_s": 10})
        async with LocalServer(config) as server:
            server.faults.script(None)  # one answer first: timeouts are then transient
            config = server.endpoint_config("m", "openai_chat", retry={**FAST_RETRY, **retry})
            async with LLMPool([config]) as pool:
                await pool.complete("m", REQUEST)
                timeouts.clear()  # the answered call's; the deadline's call follows
                with pytest.raises(InfrastructureError) as err:
                    await pool.complete("m", REQUEST)
            return err.value

    err = asyncio.run(main())
    assert err.attempts >= 2 and all("timeout" in f for f in err.failures)
    assert len(timeouts) == err.attempts
    # The deadline ended the call, not the attempt ceiling (100 attempts of 0.3 s) ...
    assert "total deadline of 1 s" in str(err), str(err)
    # ... and no attempt may run past it: each attempt starts after the one before has timed
    # out, so the timeouts handed out add up to at most the deadline (the last one clipped to
    # what is left), however loaded the machine. Unclipped they would add up to 0.3 a try.
    assert all(t == 0.3 for t in timeouts[:-1]) and timeouts[-1] <= 0.3
    assert sum(timeouts) <= 1.0 + 0.001, timeouts  # 0.001: the least timeout it hands out


def test_a_retry_after_beyond_the_deadline_fails_at_once():
    async def main():
        async with LocalServer(ServerConfig(faults={"retry_after_s": 30})) as server:
            server.faults.script("rate_limit")
            with pytest.raises(InfrastructureError) as err:
                await _one_call(server, retry={"total_timeout_s": 5})
            return err.value, list(server.log)

    err, log = asyncio.run(main())
    # refused before waiting: the backoff is checked against the deadline before its sleep
    assert err.attempts == 1 and "would pass the total deadline" in str(err)
    assert [r.status for r in log] == [429]  # one request, no retry after any wait


@pytest.mark.parametrize("status_source", ["scripted_400", "wrong_key_401"])
def test_client_errors_are_not_retried(status_source, monkeypatch):
    async def main():
        if status_source == "scripted_400":
            policy = ScriptedPolicy(["x"])
            policy.served = 1  # exhausted: the next request gets a 400
            server = LocalServer(policy=policy)
            endpoint = {}
        else:
            server = LocalServer(ServerConfig(api_key="the-right-key"))
            monkeypatch.setenv("TEST_LLM_KEY", "a-wrong-key")
            endpoint = {"api_key_env": "TEST_LLM_KEY"}
        async with server:
            with pytest.raises(RequestRejected) as err:
                await _one_call(server, retry={"max_attempts": 5}, **endpoint)
            return err.value, list(server.log)

    err, log = asyncio.run(main())
    assert err.attempts == 1 and len(log) == 1
    assert err.status == (400 if status_source == "scripted_400" else 401)


def test_a_refusal_is_fatal_when_the_endpoint_never_answered_or_the_key_is_wrong(monkeypatch):
    """Which refusals stop a sweep (`RequestRejected.fatal`): a 400 before the endpoint ever
    accepted a request (its parameters are wrong for it), a 401 always, naming the key's
    variable; a 400 after successes is one request's problem."""

    async def main():
        results = {}
        async with LocalServer(policy=ScriptedPolicy(["ok"])) as server:
            config = server.endpoint_config("m", "openai_chat", retry=FAST_RETRY)
            async with LLMPool([config]) as pool:
                await pool.complete("m", REQUEST)
                with pytest.raises(RequestRejected) as after_success:
                    await pool.complete("m", REQUEST)
            async with LLMPool([config]) as fresh:  # a new pool: no success yet
                with pytest.raises(RequestRejected) as first:
                    await fresh.complete("m", REQUEST)
            results["400 after a success"] = after_success.value
            results["400 first"] = first.value
        monkeypatch.setenv("TEST_LLM_KEY", "a-wrong-key")
        async with LocalServer(ServerConfig(api_key="the-right-key")) as server:
            with pytest.raises(RequestRejected) as wrong:
                await _one_call(server, "anthropic", api_key_env="TEST_LLM_KEY")
            results["401"] = wrong.value
        return results

    got = asyncio.run(main())
    assert not got["400 after a success"].fatal
    assert got["400 first"].fatal and "generation options" in got["400 first"].hint
    assert got["401"].fatal and got["401"].status == 401
    assert "TEST_LLM_KEY" in got["401"].hint


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_nothing_listening_is_fatal_until_the_endpoint_has_answered_once():
    """Nothing on the port before the first answer: `EndpointUnreachable` (fatal) at the first
    attempt, naming the base_url; after the endpoint has answered, the same refused connection
    (a server restarting) is retried and ends as an infrastructure error."""
    port = _free_port()

    async def main():
        config = {
            "name": "m",
            "api": "openai_chat",
            "base_url": f"http://127.0.0.1:{port}/v1",
            "retry": {**FAST_RETRY, "max_attempts": 3},
        }
        async with LLMPool([config]) as pool:
            with pytest.raises(RequestRejected) as never:
                await pool.complete("m", REQUEST)
            server = await LocalServer().start(port=port)
            await pool.complete("m", REQUEST)  # answered once
            await server.stop()
            with pytest.raises(InfrastructureError) as later:
                await pool.complete("m", REQUEST)
        return never.value, later.value

    never, later = asyncio.run(main())
    assert never.fatal and never.attempts == 1 and never.kind == "unreachable"
    assert "ClientConnectorError" in never.message
    assert f"http://127.0.0.1:{port}/v1" in never.hint and "server is running" in never.hint
    assert later.attempts == 3 and "ClientConnectorError" in later.failures[-1]


def test_transport_faults_are_retried_and_named():
    async def main():
        async with LocalServer() as server:
            server.faults.script(
                "malformed", "truncated", "drop", "overloaded", "unavailable", None
            )
            return await _one_call(server, "anthropic", retry={"max_attempts": 6})

    result = asyncio.run(main())
    assert result.attempts == 6
    malformed, truncated, dropped, overloaded, unavailable = result.failures
    assert "invalid JSON" in malformed
    assert "ClientPayloadError" in truncated
    assert "ServerDisconnectedError" in dropped
    assert "HTTP 529" in overloaded and "overloaded" in overloaded
    assert "HTTP 503" in unavailable


def test_a_persistently_malformed_body_fails_naming_the_problem():
    async def main():
        async with LocalServer(ServerConfig(faults={"rates": {"malformed": 1.0}})) as server:
            with pytest.raises(InfrastructureError) as err:
                await _one_call(server, "openai_responses", retry={"max_attempts": 2})
            return err.value

    err = asyncio.run(main())
    assert "responses response: invalid JSON" in str(err) and "EOF while parsing" in str(err)


def test_cancellation_releases_the_slot_and_the_connection():
    async def main():
        async with LocalServer(ServerConfig(latency={"mean_s": 5})) as server:
            pool = LLMPool([server.endpoint_config("m", "openai_chat")])
            task = asyncio.create_task(pool.complete("m", REQUEST))
            while server.open_connections == 0 or not server.log:
                await asyncio.sleep(0.01)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            stats = pool.stats()["m"]
            await pool.close()
            for _ in range(100):  # the server notices the closed socket within a loop turn
                if server.open_connections == 0:
                    break
                await asyncio.sleep(0.01)
            return stats, server.open_connections, list(server.log)

    stats, still_open, log = asyncio.run(main())
    assert stats.in_flight == 0 and stats.cancelled == 1 and stats.started == 1
    assert still_open == 0
    assert log[0].status is None and log[0].error == "client went away"


# -- the decisions and waits themselves ------------------------------------------------------


@pytest.mark.parametrize(
    "status,kind",
    [
        (408, "transient"),
        (409, "transient"),
        (429, "rate_limit"),
        (500, "transient"),
        (502, "transient"),
        (503, "transient"),
        (504, "transient"),
        (529, "rate_limit"),
        (400, "no"),
        (401, "no"),
        (403, "no"),
        (404, "no"),
        (413, "no"),
        (422, "no"),
    ],
)
def test_which_statuses_are_retried(status, kind):
    assert decide(status, CIMultiDict()).kind == kind


def test_retry_after_variants():
    now = datetime(2026, 11, 21, 12, 0, 0, tzinfo=timezone.utc)
    epoch = now.timestamp()

    def hint(**headers):
        h = CIMultiDict({k.replace("_", "-"): v for k, v in headers.items()})
        return server_retry_after(h, now=epoch)

    assert hint(retry_after="2") == 2.0
    assert hint(retry_after_ms="1500", retry_after="2") == 1.5  # ms is the more precise one
    date = format_datetime(now + timedelta(seconds=7), usegmt=True)
    assert hint(retry_after=date) == pytest.approx(7.0)
    # OpenAI: the reset of the exhausted limit (tokens here), as a Go duration.
    assert (
        hint(
            **{
                "x-ratelimit-remaining-requests": "10",
                "x-ratelimit-reset-requests": "1s",
                "x-ratelimit-remaining-tokens": "0",
                "x-ratelimit-reset-tokens": "6m0s",
            }
        )
        == 360
    )
    # Anthropic: RFC 3339 timestamps; with none exhausted, the latest reset.
    reset = (now + timedelta(seconds=12)).isoformat().replace("+00:00", "Z")
    soon = (now + timedelta(seconds=3)).isoformat().replace("+00:00", "Z")
    assert hint(
        **{"anthropic-ratelimit-requests-reset": soon, "anthropic-ratelimit-tokens-reset": reset}
    ) == pytest.approx(12.0)
    assert hint(
        **{
            "anthropic-ratelimit-requests-remaining": "0",
            "anthropic-ratelimit-requests-reset": soon,
            "anthropic-ratelimit-tokens-reset": reset,
        }
    ) == pytest.approx(3.0)
    assert hint() is None and hint(retry_after="soon") is None
    assert hint(retry_after="-5") == 0.0


@pytest.mark.parametrize(
    "text,seconds",
    [
        ("1s", 1),
        ("6m0s", 360),
        ("20ms", 0.02),
        ("1h2m3.5s", 3723.5),
        ("0.5s", 0.5),
        ("7", 7),
        ("", None),
        ("soon", None),
    ],
)
def test_go_durations(text, seconds):
    assert parse_go_duration(text) == (pytest.approx(seconds) if seconds is not None else None)


def test_backoff_is_exponential_with_jitter_and_never_undercuts_a_hint():
    policy = RetryPolicy(backoff_base_s=1, backoff_max_s=10)
    rng = random.Random(0)
    for attempt, ceiling in [(1, 1), (2, 2), (3, 4), (4, 8), (5, 10), (9, 10)]:
        delays = [backoff_delay(attempt, policy, None, rng) for _ in range(200)]
        assert ceiling / 2 <= min(delays) and max(delays) <= ceiling
        assert max(delays) - min(delays) > ceiling / 4  # jittered, not fixed
    hinted = [backoff_delay(1, policy, 2.0, rng) for _ in range(200)]
    assert min(hinted) >= 2.0 and max(hinted) <= 2.2


def test_a_429_pauses_the_whole_endpoint():
    """One call told to wait holds back the calls behind it too: the server asked the
    endpoint, not one call, to slow down."""

    async def main():
        async with LocalServer(ServerConfig(faults={"retry_after_s": 1})) as server:
            server.faults.script("rate_limit")
            config = server.endpoint_config("m", "openai_chat", retry=FAST_RETRY)
            async with LLMPool([config]) as pool:
                first = asyncio.create_task(pool.complete("m", REQUEST))
                while not server.log or server.log[0].status is None:
                    await asyncio.sleep(0.005)
                await pool.complete("m", REQUEST)
                await first
            return list(server.log)

    log = asyncio.run(main())
    assert log[0].status == 429
    assert all(r.received_s - log[0].received_s >= 1.0 for r in log[1:])


def test_cancelling_hundreds_of_looping_callers_ends_every_one():
    """Callers that loop on complete() must all stop on cancel(), whatever step they are in
    (queued, admitted, sending, reading); a swallowed cancellation would leave one running."""

    async def main():
        async with LocalServer(ServerConfig(latency={"mean_s": 0.01})) as server:
            pool = LLMPool([server.endpoint_config("m", "openai_chat")])

            async def caller():
                while True:
                    await pool.complete("m", REQUEST)

            tasks = [asyncio.create_task(caller()) for _ in range(300)]
            await asyncio.sleep(0.5)
            for task in tasks:
                task.cancel()
            _, pending = await asyncio.wait(tasks, timeout=10)
            stats = pool.stats()["m"]
            await pool.close()
            return len(pending), stats

    pending, stats = asyncio.run(main())
    assert pending == 0
    assert stats.in_flight == 0 and stats.cancelled == 300
    assert stats.started == stats.succeeded + stats.cancelled
