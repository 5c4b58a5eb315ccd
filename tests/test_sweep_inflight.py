"""The adaptive in-flight limit (vabench.tuning.inflight).

The controller is driven by a closed-loop model of a sweep, where the answer is known: N
episodes in flight share a stage of K parallel servers taking `s` seconds per decision, after
a model latency L. Decisions complete at X = min(N / (L + s), K / s) per second, so one takes
R = N / X: flat until the knee N* = K (L + s) / s, linear beyond it. The limit must settle past
the knee (at least 90 % of the stage's throughput) with a short queue (decisions at most twice
their unloaded time), reach the ceiling when nothing saturates, and never move when fixed.
The gate must admit at most the limit, in arrival order, and lose no slot to a cancelled
waiter. A real sweep starts with one episode in flight, so its first episode ends before the
others start, and reports the limit and why.
"""

from __future__ import annotations

import asyncio
import json
import random

import pytest

from vabench.sweep.__main__ import main
from vabench.tuning.inflight import InFlight, LimitController


def decision_time(n: int, latency: float, service: float, servers: int) -> float:
    throughput = min(n / (latency + service), servers / service)
    return n / throughput


def drive(controller: LimitController, windows: int, noise: float = 0.1, **stage) -> list[int]:
    """Feed `windows` windows of decisions timed by the stage at the current limit; the limit
    after each window."""
    rng = random.Random(0)
    limits = []
    for _ in range(windows):
        before = controller.windows
        while controller.windows == before:
            r = decision_time(controller.limit, **stage)
            controller.observe(("model", "active"), r * rng.uniform(1 - noise, 1 + noise))
        limits.append(controller.limit)
    return limits


@pytest.mark.parametrize(
    "stage",
    [
        {"latency": 2.0, "service": 0.01, "servers": 4},  # knee at 804: real model latency
        {"latency": 0.0, "service": 0.2, "servers": 2},  # knee at 2: a 2-core laptop, no latency
        {"latency": 0.5, "service": 0.05, "servers": 8},  # knee at 88
    ],
)
def test_the_limit_settles_just_past_the_knee(stage):
    knee = stage["servers"] * (stage["latency"] + stage["service"]) / stage["service"]
    controller = LimitController(ceiling=4096)
    limits = drive(controller, 200, **stage)
    settled = limits[-50:]
    best = decision_time(1, **stage)
    for n in settled:
        throughput = n / decision_time(n, **stage)
        # full throughput: at least 90 % of what the stage can do
        assert throughput >= 0.9 * stage["servers"] / stage["service"], (n, knee)
        # and a short queue: a decision takes at most twice its unloaded time
        assert decision_time(n, **stage) <= 2 * best + 1e-9, (n, knee)
    assert not controller.slow_start


def test_without_saturation_the_limit_reaches_the_ceiling_and_says_so():
    controller = LimitController(ceiling=300)
    limits = drive(controller, 40, latency=2.0, service=0.001, servers=10_000)
    assert limits[-1] == 300
    assert "executor.max_episodes = 300" in controller.reason
    # slow start: doubling from one episode
    assert limits[:4] == [2, 4, 8, 16]


def test_one_window_never_more_than_halves_the_limit():
    controller = LimitController(ceiling=1000)
    drive(controller, 30, latency=1.0, service=0.0001, servers=10_000)  # grow first
    before = controller.limit
    for _ in range(max(4, before // 2)):
        controller.observe(("model", "active"), 1000.0)  # a catastrophic window
    assert controller.limit >= before // 2


def test_a_fixed_limit_never_moves():
    controller = LimitController(ceiling=256, fixed=12)
    assert controller.limit == 12 and controller.reason == "executor.in_flight = 12"
    for _ in range(100):
        assert not controller.observe(("m", "active"), 5.0)
    assert controller.limit == 12
    assert LimitController(ceiling=8, fixed=12).limit == 8


def test_the_gate_admits_at_most_the_limit_in_arrival_order_and_loses_no_slot():
    async def scenario() -> None:
        gate = InFlight(ceiling=10, fixed=2)
        order: list[int] = []
        release = asyncio.Event()

        async def episode(i: int) -> None:
            async with gate.slot():
                order.append(i)
                assert gate.in_flight <= gate.limit
                await release.wait()

        tasks = [asyncio.create_task(episode(i)) for i in range(6)]
        await asyncio.sleep(0.01)
        assert order == [0, 1] and gate.in_flight == 2
        tasks[2].cancel()  # a waiter cancelled before its turn takes no slot with it
        await asyncio.sleep(0.01)
        release.set()
        await asyncio.gather(*tasks, return_exceptions=True)
        assert order == [0, 1, 3, 4, 5]
        assert gate.in_flight == 0 and gate.peak == 2

    asyncio.run(scenario())


def test_a_raised_limit_admits_waiters_at_once():
    async def scenario() -> None:
        gate = InFlight(ceiling=64)  # adaptive: starts at one
        entered = asyncio.Event()
        hold = asyncio.Event()
        admitted: list[int] = []

        async def episode(i: int) -> None:
            async with gate.slot():
                admitted.append(i)
                entered.set()
                await hold.wait()

        tasks = [asyncio.create_task(episode(i)) for i in range(4)]
        await entered.wait()
        assert admitted == [0]
        for _ in range(4):  # a window of unloaded decisions: slow start doubles
            gate.observe(("m", "active"), 1.0)
        await asyncio.sleep(0)
        assert gate.limit == 2 and admitted == [0, 1]
        hold.set()
        await asyncio.gather(*tasks)

    asyncio.run(scenario())


SWEEP = """\
name: inflight
models:
  - {name: local, api: openai_chat, base_url: embedded}
embedded_server: {policy: conversation_hash, latency: {mean_s: 0.05}}
tracks: [active]
summaries: none
tasks: [grasp_single_cube]
seeds: {verified: 6}
runs: 1
step_budget: 3
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
executor: {kind: local}
"""


def test_a_sweep_starts_with_one_episode_so_the_first_ends_before_the_rest_start(tmp_path, capsys):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(SWEEP)
    out = tmp_path / "out"
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    records = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert len(records) == 6
    starts = sorted(r["started_at"] for r in records)
    first_end = min(r["started_at"] + r["wall_s"] for r in records)
    # the limit stays at one until a window of 4 decisions ends: after the first episode's 3.
    # Records keep times to the millisecond (two roundings in first_end): the next episode may
    # start in the millisecond the first one ends.
    assert first_end <= starts[1] + 0.001
    out_text = capsys.readouterr().out
    # the episodes' limit beside the running count; "in flight" is the model calls alone
    assert "in flight" in out_text
    assert " at once" in out_text or "(limit now " in out_text
