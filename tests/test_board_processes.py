"""The limit board of worker processes (`llm_pool.board_socket`): real processes, each with its own
LLM pool, take their admissions and spend reservations from one board in this process, over
its socket, and call one embedded server that enforces its rate limit. Together they never
exceed it (the server refuses nothing); a spend cap holds exactly across them; a process that
dies gives back its slots. The same processes keeping their own limits exceed the server (the
control). Windows are 1 s instead of a minute: the code is the same.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import signal
import time

import pytest

from vabench.llm_pool import ChatRequest, LLMPool, Turn
from vabench.llm_pool.board_socket import BoardAddress, BoardServer, joined
from vabench.llm_pool.errors import SpendCapReached
from vabench.llm_pool.limit_board import LimitBoard
from vabench.llm_pool.server import ServerConfig
from vabench.llm_pool.spend import SpendCaps
from vabench.llm_pool.testing import max_in_window, server_in_thread

R = 6
LIMITS = {"rpm": R, "period_s": 1.0, "burst_s": 0.2, "max_concurrency": 8}
SERVER = ServerConfig(rpm=R, rate_period_s=1.0, latency={"mean_s": 0.02})
RETRY = {"max_attempts": 30, "backoff_base_s": 0.05, "backoff_max_s": 0.2}
PRICES = {"input": 1000.0, "output": 1000.0}  # a call of ~110 tokens: ~$0.11


def _worker(endpoint: dict, board: BoardAddress | None, calls: int, answers) -> None:
    """A sweep's worker process: its own pool, the board's limits (None: its own)."""

    async def main() -> list[float]:
        request = ChatRequest([Turn.user("ping")])
        if board is None:
            async with LLMPool([endpoint]) as pool:
                results = await asyncio.gather(*(pool.complete("m", request) for _ in range(calls)))
            return [r.cost_usd for r in results]
        async with joined(board) as limits:
            pool = LLMPool([endpoint], shared_limits=limits, spend_caps=limits.spend)
            async with pool:
                if not board.capped:
                    done = await asyncio.gather(
                        *(pool.complete("m", request) for _ in range(calls))
                    )
                    return [r.cost_usd for r in done]
                costs = []  # one call at a time, until the cap refuses one
                for _ in range(calls):
                    try:
                        costs.append((await pool.complete("m", request)).cost_usd)
                    except SpendCapReached:
                        return [*costs, -1.0]
                return costs

    answers.put((os.getpid(), asyncio.run(main())))


def run_workers(
    n: int, calls: int, shared: bool, caps: SpendCaps | None = None, prices: dict | None = None
) -> tuple[list, list, dict]:
    """`n` worker processes of `calls` calls each against a server enforcing `R` a second;
    returns (each worker's costs, the server's log as (arrival, status), the board's spend)."""
    with server_in_thread(SERVER) as server:
        endpoint = server.endpoint_config(
            "m",
            "openai_chat",
            limits=LIMITS,
            generation={"max_output_tokens": 100},
            retry=RETRY,
            **({"prices": prices} if prices else {}),
        )
        board = BoardServer(LimitBoard({"m": LIMITS}, caps))
        address = BoardAddress(board.start(), ("m",), caps is not None)
        context = multiprocessing.get_context("spawn")
        answers = context.SimpleQueue()
        workers = [
            context.Process(
                target=_worker, args=(endpoint, address if shared else None, calls, answers)
            )
            for _ in range(n)
        ]
        try:
            for w in workers:
                w.start()
            costs = [answers.get()[1] for _ in workers]
            for w in workers:
                w.join(30)
            spent = board.call(board.board.spent)
            held = board.stats()["m"]["held"]
        finally:
            board.close()
        assert not held  # every holder gave back its slots
        log = [(r.received_s, r.status) for r in server.log]
    return costs, log, spent


def test_two_worker_processes_on_one_board_keep_the_servers_rate():
    costs, log, _ = run_workers(2, 9, shared=True)
    assert [len(c) for c in costs] == [9, 9] and all(c >= 0 for w in costs for c in w)
    assert [s for _, s in log].count(429) == 0  # the server refused nothing
    assert len(log) == 18
    assert max_in_window([(t, 1.0) for t, _ in log], 1.0) <= R


def test_two_worker_processes_with_their_own_limits_exceed_it():
    """The control: the same processes, each keeping the limit for itself, send twice the rate
    and the server refuses some (each retried until it passes)."""
    _, log, _ = run_workers(2, 9, shared=False)
    assert [s for _, s in log].count(429) > 0


def test_a_spend_cap_holds_to_the_cent_across_two_worker_processes():
    """$0.50 over two processes calling one at a time until refused: a call costs ~$0.035 and
    its upper bound (100 output tokens + its input, at $1000 a million) is ~$0.11. Counting
    alone, each process would spend up to the cap (together ~$0.8-1.0); on the board they
    stop together at it, each call's upper bound reserved before it went."""
    caps = SpendCaps({"m": 0.5}, None, {})
    costs, log, spent = run_workers(2, 30, shared=True, caps=caps, prices=PRICES)
    paid = [c for w in costs for c in w if c >= 0]
    assert all(w[-1] == -1.0 for w in costs)  # each process was refused in the end
    assert sum(paid) <= 0.5 + 1e-9
    assert abs(spent["m"] - sum(paid)) < 1e-9  # the board counted what the calls cost
    assert len([s for _, s in log if s == 200]) == len(paid)  # nothing sent past the cap
    assert sum(paid) > 0.5 - 2 * 0.12  # refused only when the next upper bound would cross


def _holder_that_dies(address: BoardAddress, ready) -> None:
    async def main() -> None:
        async with joined(address, "doomed") as limits:
            slots = limits(_endpoint_of_board())
            assert slots is not None
            await slots.concurrency.acquire()
            await slots.concurrency.acquire()
            ready.set()
            await asyncio.sleep(3600)

    asyncio.run(main())


def _endpoint_of_board():
    from vabench.llm_pool.config import load_endpoints

    return load_endpoints(
        [{"name": "m", "api": "openai_chat", "base_url": "http://x/v1", "limits": LIMITS}]
    )[0]


def test_a_dead_workers_slots_come_back_to_the_board():
    board = BoardServer(LimitBoard({"m": LIMITS}))
    address = BoardAddress(board.start(), ("m",), False)
    context = multiprocessing.get_context("spawn")
    ready = context.Event()
    worker = context.Process(target=_holder_that_dies, args=(address, ready))
    try:
        worker.start()
        assert ready.wait(60)
        assert board.stats()["m"]["held"] == {"doomed": 2}
        os.kill(worker.pid, signal.SIGKILL)
        worker.join(10)
        for _ in range(100):
            if not board.stats()["m"]["held"]:
                break
            time.sleep(0.05)
        stats = board.stats()["m"]
        assert stats["held"] == {} and stats["in_flight"] == 0
    finally:
        if worker.is_alive():
            worker.kill()
        board.close()


@pytest.mark.parametrize("method", ["admit", "nonexistent"])
def test_a_bad_request_answers_an_error_and_the_board_lives_on(method):
    from vabench.llm_pool.board_socket import SocketChannel

    board = BoardServer(LimitBoard({"m": LIMITS}))
    address = board.start()

    async def main() -> tuple[str, object]:
        channel = await SocketChannel.connect(address, "h")
        try:
            with pytest.raises(RuntimeError) as err:
                await channel.call(method, "no-such-endpoint", "h", [1.0])
            return str(err.value), await channel.call("admit", "m", "h", [1.0])
        finally:
            await channel.close()

    try:
        message, after = asyncio.run(main())
    finally:
        board.close()
    assert ("no endpoint" in message) or ("nonexistent" in message)
    assert after[0] == 1


SWEEP = """\
name: board
models:
  - name: limited
    api: openai_chat
    base_url: {url}
    limits: {{rpm: {rpm}, period_s: {period}, max_concurrency: 8}}
    retry: {{max_attempts: 20, backoff_base_s: 0.05, backoff_max_s: 0.2}}
tracks: [active]
tasks: [grasp_single_cube, handover_horizontal_block]
seeds: {{verified: 2}}
runs: 1
step_budget: 3
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
executor: {{kind: processes, max_tasks: 2}}
"""


def test_a_sweeps_two_worker_processes_keep_the_servers_rate(tmp_path, caplog):
    """Through the sweep command: two cells in two worker processes call one server that
    enforces 4 requests per 2 s; the parent's board keeps the model's `rpm` for both."""
    import logging

    from vabench.sweep.__main__ import main

    rpm, period = 4, 2.0
    server_config = ServerConfig(policy="conversation_hash", rpm=rpm, rate_period_s=period)
    with server_in_thread(server_config) as server:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(SWEEP.format(url=server.base_url("openai_chat"), rpm=rpm, period=period))
        with caplog.at_level(logging.INFO, logger="vabench.sweep"):
            assert main([str(cfg), "--out", str(tmp_path / "out"), "--plain", "--no-report"]) == 0
        log = [(r.received_s, r.status) for r in server.log]
    assert "one limit board for every engine keeps the limits of limited" in caplog.text
    assert len(log) >= 8 and [s for _, s in log].count(429) == 0
    assert max_in_window([(t, 1.0) for t, _ in log], period) <= rpm
