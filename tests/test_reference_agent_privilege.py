"""The reference agent's smoke run: every request it receives holds no evaluator-only field.

One short episode per kind of track the agent runs (a single-arm family under the active and
the passive protocol, a dual-arm family, a held-out variant, the basket), each against the
embedded server with its request bodies captured and the evaluator's state probed before every
reply (`engine_util.ProbingPolicy` around `ReferenceServo`). Every captured body is checked
with `visibility.find_leaks` against that episode's secrets (object positions as sampled and at
every request, the seed, every camera position, model ids, latch, checkpoint and body names).
The agent's own replies (its memo carries positions it estimated from the images) come back as
assistant turns: model output, which the check skips, as it does for any model.
"""

from __future__ import annotations

import asyncio

import pytest
from engine_util import EpisodeRun, run_scripted_async, secrets_of

from vabench.agent.conversation import ContextLimits
from vabench.agent.services import EngineSettings
from vabench.agent.visibility import find_leaks
from vabench.reference_agent import ReferenceServo
from vabench.render.worker import ImageSettings, RenderPool

SMOKE = (
    ("grasp_single_cube", "active"),
    ("grasp_single_cube", "passive"),
    ("lift_pot", "active"),
    ("place_cube_on_cube_heldout", "active"),
    ("put_everything_in_basket", "active"),
)
BUDGET = 12  # steps: enough for the agent to look, locate and start acting
IMAGE = ImageSettings(320, 240)  # the agent finds the objects at this size (tiny ones: not)
# The basket episode runs with a context window small enough to be compacted within the budget
# (its real episodes are long and compact several times): the summary request is inspected
# like any other, and the episode must go on after it.
COMPACTED = "put_everything_in_basket"
TINY = EngineSettings(limits=ContextLimits(window_tokens=6_000, output_reserve_tokens=1_000))


@pytest.fixture(scope="module")
def runs() -> dict[tuple[str, str], EpisodeRun]:
    async def all_runs(pool: RenderPool) -> list[EpisodeRun]:
        gate = asyncio.Semaphore(2)

        async def one(task: str, protocol: str) -> EpisodeRun:
            async with gate:
                return await run_scripted_async(
                    task,
                    [],
                    pool,
                    protocol=protocol,
                    budget=BUDGET,
                    inner=ReferenceServo(),
                    image=IMAGE,
                    settings=TINY if task == COMPACTED else None,
                )

        return list(await asyncio.gather(*(one(t, p) for t, p in SMOKE)))

    with RenderPool(workers=1, max_size=(IMAGE.width, IMAGE.height), timeout_s=120) as pool:
        return dict(zip(SMOKE, asyncio.run(all_runs(pool)), strict=True))


@pytest.mark.parametrize("episode", SMOKE, ids=[f"{t}-{p}" for t, p in SMOKE])
def test_no_request_of_the_smoke_run_leaks(runs, episode):
    run = runs[episode]
    assert run.result.status in ("success", "failure"), run.result.error
    assert len(run.bodies) == run.result.model_calls == len(run.probes) > 0
    secrets = secrets_of(run)
    assert any(s.name.startswith("object") for s in secrets)
    for i, (api, raw) in enumerate(run.bodies):
        leaks = find_leaks(raw, secrets)
        assert not leaks, f"request {i} ({api}):\n" + "\n".join(map(str, leaks))


NOT_YET: set[tuple[str, str]] = set()  # tracks where the agent stops at once


@pytest.mark.parametrize(
    "episode",
    [pytest.param(e, marks=pytest.mark.xfail(strict=True)) if e in NOT_YET else e for e in SMOKE],
    ids=[f"{t}-{p}" for t, p in SMOKE],
)
def test_the_smoke_run_acts(runs, episode):
    """The requests inspected above come from an agent that acts, not one that stops at once
    (so they hold robot states after moves, executed actions and the agent's memo)."""
    assert runs[episode].result.robot_actions > 0


def test_a_compacted_episode_goes_on(runs):
    """History compaction inside a real episode: the engine asks for a summary, records the
    compaction with its step, and the agent (whose memo is in the kept turns) acts on."""
    run = runs[COMPACTED, "active"]
    compactions = run.of_type("compaction")
    assert run.result.compactions == len(compactions) >= 1, run.result.error
    assert all(isinstance(e["step"], int) and e["step"] >= 1 for e in compactions)
    first = min(e["step"] for e in compactions)
    assert any(e["step"] > first for e in run.of_type("action"))
