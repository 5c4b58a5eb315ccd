"""Many episodes of one task over one simulator batch: robot actions that arrive close together
run in one simulator call, and batching never changes an episode's trajectory.

64 concurrent episodes against the embedded server (random valid actions, random latency);
afterwards every episode's executed decisions are replayed alone in a fresh one-slot batch and
must reproduce the batched run bit for bit (final qpos) and outcome for outcome.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from vabench.agent.engine import Episode, EpisodeSpec
from vabench.agent.services import task_services
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.render.worker import ImageSettings, RenderPool
from vabench.tasks import get_task
from vabench.tasks.manifests import verified_seeds
from vabench.tasks.task_batch import TaskBatch

TASK = "grasp_single_cube"
TINY = ImageSettings(64, 48, 90)


@pytest.fixture(scope="module")
def render_pool():
    with RenderPool(workers=1, max_size=(64, 48)) as pool:
        yield pool


async def run_concurrent(n: int, steps: int, backend: str, render_pool: RenderPool):
    task = get_task(TASK)
    seeds = verified_seeds(TASK)
    config = ServerConfig(
        policy="random_action",
        policy_options={"seed": 11},
        latency={"mean_s": 0.15, "dist": "uniform", "spread": 0.9},
        seed=5,
    )
    async with LocalServer(config) as server:
        endpoints = [server.endpoint_config("local", "openai_chat")]
        async with (
            LLMPool(endpoints) as llm,
            task_services(
                task, n, llm, render_pool, backend=backend, image=TINY, sim_window_s=0.02
            ) as svc,
        ):
            episodes = [
                Episode(EpisodeSpec(TASK, seeds[i % len(seeds)], "local", step_budget=steps), svc)
                for i in range(n)
            ]
            results = await asyncio.gather(*(e.run() for e in episodes))
            runs = [(r, e.rec.events) for r, e in zip(results, episodes, strict=True)]
            return task, runs, svc.sim.counters, svc.sim.stats, svc.sim.batch


def replay_alone(tb: TaskBatch, seed: int, actions: list[dict]):
    """The decisions replayed in a one-slot batch (reused: a reset starts from scratch)."""
    assert tb.reset([0], [seed])[0].ok
    outcomes = [tb.step([a])[0] for a in actions]
    return tb.batch.qpos()[0], outcomes


def check_against_replays(task, runs, batch, backend: str) -> None:
    assert all(r.scored for r, _ in runs), [r.error for r, _ in runs if not r.scored]
    alone = TaskBatch(task, 1, backend=backend)
    for r, events in runs:
        slot = next(e["slot"] for e in events if e["type"] == "reset")
        decisions = [e["decision"] for e in events if e["type"] == "decision"]
        actions = [e for e in events if e["type"] == "action"]
        assert len(decisions) == len(actions) == r.robot_actions
        qpos, outcomes = replay_alone(alone, r.seed, decisions)
        np.testing.assert_array_equal(qpos, batch.batch.qpos()[slot])
        for out, e in zip(outcomes, actions, strict=True):
            assert (out.result.valid, out.result.planner_success, out.progress, out.success) == (
                e["valid"],
                e["planner_success"],
                e["progress"],
                e["success"],
            )


def test_sixty_four_episodes_share_simulator_calls_and_match_replays_alone(render_pool):
    task, runs, counters, stats, batch = asyncio.run(run_concurrent(64, 5, "c", render_pool))
    # The episodes ran concurrently on one batch: robot actions were executed in far fewer
    # simulator calls than there were actions.
    assert counters.actions == sum(r.robot_actions for r, _ in runs) >= 64 * 4
    assert counters.step_calls * 4 <= counters.actions, (counters, stats)
    assert counters.reset_calls < 64
    check_against_replays(task, runs, batch, "c")


@pytest.mark.slow
def test_mjx_batching_matches_replays_alone(render_pool):
    task, runs, counters, _, batch = asyncio.run(run_concurrent(8, 3, "mjx", render_pool))
    assert counters.step_calls < counters.actions
    check_against_replays(task, runs, batch, "mjx")
