"""Episodes whose model replies as real models do (C MuJoCo, tiny images, the embedded server
over HTTP): every shape ends as a decision, a repair that says what happened, or a named,
scored stop reason; none as an infrastructure error or an unscored rejection."""

from __future__ import annotations

import json
from typing import Any

import pytest
from engine_util import STOP, body_json, move, run_scripted, tool, user_texts

from vabench.llm_pool.apis.base import IncomingRequest
from vabench.llm_pool.policies import PolicyError, ScriptedPolicy
from vabench.render.worker import RenderPool

TASK = "grasp_single_cube"
SEED = 1000
VLLM_CONTEXT_ERROR = (
    "This model's maximum context length is 32768 tokens. However, you requested 40312 tokens "
    "(36216 in the messages, 4096 in the completion). Please reduce the length of the messages "
    "or completion."
)


@pytest.fixture(scope="module")
def pool():
    with RenderPool(workers=1, timeout_s=60) as p:
        yield p


def chat_body(message: dict[str, Any], finish: str = "stop") -> dict[str, Any]:
    return {
        "body": {
            "id": "chatcmpl-1",
            "model": "m",
            "choices": [
                {"index": 0, "message": {"role": "assistant", **message}, "finish_reason": finish}
            ],
            "usage": {"prompt_tokens": 100, "completion_tokens": 10},
        }
    }


def test_content_as_text_parts_is_read_and_executed(pool):
    parts = [{"type": "text", "text": "Raising the gripper.\n"}, {"type": "text", "text": move()}]
    run = run_scripted(TASK, [chat_body({"content": parts}), STOP], pool, seed=SEED, budget=3)
    r = run.result
    assert (r.status, r.stop_reason, r.steps_used, r.invalid_outputs) == (
        "failure",
        "model_stop",
        1,
        0,
    )
    (action,) = run.of_type("action")
    assert action["valid"] and "z+10mm" in action["label"], action


def test_reasoning_only_gets_its_repair_and_the_episode_goes_on(pool):
    script = [chat_body({"content": None, "reasoning_content": move()}), move(), STOP]
    run = run_scripted(TASK, script, pool, seed=SEED, budget=3)
    r = run.result
    assert (r.stop_reason, r.steps_used, r.invalid_outputs, r.empty_replies) == (
        "model_stop",
        1,
        1,
        1,
    )
    assert run.of_type("reply")[0]["reasoning"] == move()
    repair = user_texts(body_json(run.bodies[1][1]))[-1]
    assert "your answer came in the reasoning channel only" in repair


@pytest.mark.parametrize("api", ["openai_chat", "openai_responses", "anthropic"])
def test_refusals_end_the_episode_refused_after_two_repairs(pool, api):
    refusal = {"text": "I can't help with controlling that robot.", "finish_reason": "refusal"}
    run = run_scripted(TASK, [refusal] * 3, pool, seed=SEED, budget=3, api=api)
    r = run.result
    assert (r.status, r.stop_reason, r.scored) == ("failure", "refused", True)
    assert (r.refusals, r.invalid_outputs, r.steps_used) == (3, 3, 0)
    assert [e["kind"] for e in run.of_type("rejection")] == ["refusal"] * 3
    assert [e["finish_reason"] for e in run.of_type("reply")] == ["refusal"] * 3
    repair = user_texts(body_json(run.bodies[1][1]))[-1]
    assert "your reply was a refusal (I can't help with controlling that robot.)" in repair
    assert run.of_type("end")[0]["stop_reason"] == "refused"


def test_replies_cut_at_the_output_limit_end_truncated(pool):
    """The embedded server cuts a reply at max_output_tokens, as a real server does."""
    long = "Let me reason about the scene at length. " * 40 + move()
    run = run_scripted(
        TASK,
        [long] * 3,
        pool,
        seed=SEED,
        budget=3,
        endpoint={"generation": {"max_output_tokens": 32}},
    )
    r = run.result
    assert (r.status, r.stop_reason, r.truncations, r.invalid_outputs) == (
        "failure",
        "truncated",
        3,
        3,
    )
    assert [e["finish_reason"] for e in run.of_type("reply")] == ["length"] * 3
    repair = user_texts(body_json(run.bodies[1][1]))[-1]
    assert (
        "your reply was cut off at the output limit (32 tokens): reply with the JSON object only"
        in repair
    )


class ContextBound:
    """Answers like a server whose context holds `max_user_turns` user messages: a longer
    request gets vLLM's 400 (so does every request after the first `served_at_most`); the
    compaction's summary request (one text-only turn) gets a summary; other requests the
    scripted replies."""

    def __init__(self, replies: list[str], max_user_turns: int, served_at_most: int = 1000):
        self.script = ScriptedPolicy(replies)
        self.max_user_turns = max_user_turns
        self.served_at_most = served_at_most
        self.rejected = 0

    async def respond(self, request: IncomingRequest) -> str:
        if len(request.chat.turns) == 1 and not request.chat.images:
            return "Summary: the gripper has not moved; geometry was checked."
        users = sum(t.role == "user" for t in request.chat.turns)
        if users > self.max_user_turns or self.script.served >= self.served_at_most:
            self.rejected += 1
            raise PolicyError(VLLM_CONTEXT_ERROR, status=400)
        reply = await self.script.respond(request)
        assert isinstance(reply, str)
        return reply


def test_a_context_rejection_on_the_first_call_is_a_scored_failure_not_a_stopped_sweep(pool):
    policy = ContextBound([STOP], max_user_turns=0)
    run = run_scripted(TASK, [], pool, seed=SEED, budget=3, inner=policy)
    r = run.result
    assert (r.status, r.stop_reason, r.scored) == ("failure", "context_exceeded", True)
    assert "maximum context length is 32768" in (r.error or "")
    assert not run.of_type("endpoint_refused")
    assert len(run.of_type("context_exceeded")) == 1


def test_a_context_rejection_compacts_and_retries_once(pool):
    verify = tool("geometry.verify")
    policy = ContextBound([verify] * 10 + [STOP], max_user_turns=8)
    run = run_scripted(TASK, [], pool, seed=SEED, budget=3, inner=policy)
    r = run.result
    assert (r.status, r.stop_reason) == ("failure", "model_stop"), r.error
    assert policy.rejected == 1 and r.compactions == 1
    assert r.model_calls == 12  # 11 decisions' calls and the summary
    types = [e["type"] for e in run.events]
    at = types.index("context_exceeded")
    assert types[at + 1 : at + 4] == ["compaction", "request", "reply"]


def test_a_context_still_too_small_after_compaction_ends_context_exceeded(pool):
    verify = tool("geometry.verify")
    policy = ContextBound([verify] * 10, max_user_turns=100, served_at_most=8)
    run = run_scripted(TASK, [], pool, seed=SEED, budget=3, inner=policy)
    r = run.result
    assert (r.status, r.stop_reason, r.compactions) == ("failure", "context_exceeded", 1)
    assert policy.rejected == 2 and "after one compaction" in (r.error or "")


def test_the_models_context_window_sets_the_compaction(pool):
    run = run_scripted(TASK, [STOP], pool, seed=SEED, budget=3, endpoint={"context_window": 32_768})
    limits = run.episode.conv.limits
    assert (limits.window_tokens, limits.compact_above) == (
        32_768,
        int(0.8 * 32_768) - 8_192,  # the estimate plus the reserve at 0.8 of the window
    )
    default = run_scripted(TASK, [STOP], pool, seed=SEED, budget=3).episode.conv.limits
    assert default.window_tokens == 262_144


def test_result_files_without_the_new_counters_still_read():
    from vabench.agent.records import EpisodeResult

    old = {
        "task": TASK,
        "seed": SEED,
        "model": "m",
        "protocol": "active",
        "run": 0,
        "status": "failure",
        "success": False,
        "stop_reason": "invalid_output",
        "step_budget": 3,
        "n_checkpoints": 2,
    }
    r = EpisodeResult.model_validate_json(json.dumps(old))
    assert (r.refusals, r.truncations, r.empty_replies) == (0, 0, 0)
