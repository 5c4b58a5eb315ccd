"""History compaction inside a real episode: the engine asks the model for a summary, records
the compaction with the step it happened at, and the episode goes on (a long episode, such as
the reference agent's basket task, compacts several times)."""

from __future__ import annotations

from engine_util import STOP, move, run_scripted

from vabench.agent.conversation import ContextLimits
from vabench.agent.engine import EngineSettings
from vabench.render.worker import RenderPool

# small enough that a handful of observations (about 1,000 tokens each) crosses it
TINY = EngineSettings(limits=ContextLimits(window_tokens=5_000, output_reserve_tokens=1_000))


def test_an_episode_compacts_and_goes_on():
    script = [move("z", "+", 5), move("z", "-", 5)] * 3 + [STOP]
    with RenderPool(workers=1, timeout_s=60) as pool:
        run = run_scripted("grasp_single_cube", script, pool, budget=10, settings=TINY)
    assert run.result.stop_reason != "harness_error", run.result.error
    compactions = run.of_type("compaction")
    assert run.result.compactions == len(compactions) >= 1
    steps = [e["step"] for e in compactions]
    assert all(isinstance(s, int) and 1 <= s <= run.result.steps_used + 1 for s in steps)
