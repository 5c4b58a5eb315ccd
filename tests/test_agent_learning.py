"""The learning stage (FACTS "Demonstration protocol"): the demonstration tools, the learning
gate, the summary schema and the session's budgets.

Sessions run against the embedded server's scripted policy over real HTTP (as the engine tests
do), on synthetic demonstrations of solid-colour JPEG frames: the session never looks inside a
frame, so no simulator or renderer is needed.
"""

from __future__ import annotations

import asyncio
import io
import json
import re
from dataclasses import dataclass
from typing import Any

import pytest
from engine_util import FAST_RETRY, body_json, count_images, reply, tool, user_texts
from PIL import Image as PILImage

from vabench import protocol as P
from vabench.agent.demonstration import MIN_DISTINCT_FRAMES, DemoFrames, learning_prompt
from vabench.agent.learning import LearningLimits, LearningResult, learn_summary, read_result
from vabench.agent.records import EpisodeRecorder
from vabench.agent.summary import (
    MAX_LIST_ITEMS,
    MAX_TEXT_CHARS,
    REQUIRED_FIELDS,
    DemoSummary,
    parse_summary,
    summary_text,
)
from vabench.llm_pool.policies import ScriptedPolicy
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer


@dataclass(frozen=True)
class FakeTask:
    name: str = "grasp_single_cube"
    instruction: str = "Pick up the red cube and lift it off the table."
    arms: tuple[str, ...] = ("right",)


N_FRAMES = 12


def jpeg(i: int) -> bytes:
    buf = io.BytesIO()
    PILImage.new("RGB", (32, 24), (20 * i % 256, 100, 200)).save(buf, format="JPEG")
    return buf.getvalue()


DEMO = DemoFrames([jpeg(i) for i in range(N_FRAMES)], fps=3.0, label="demo-a")

SUMMARY: dict[str, Any] = {
    "grasp_object_part": "the red cube, its body",
    "grasp_region": "the two side faces facing left and right",
    "grasp_height_or_depth": "about mid-height of the cube, 15 mm below its top face",
    "finger_placement": "fingers centred on opposite faces, closing along x",
    "approach_strategy": "align above the cube from the top view, then descend vertically",
    "posture_or_rotation": "fingers vertical, rotated so the jaws are parallel to the faces",
    "pre_close_checks": ["both fingers below the top face", "cube centred between the fingers"],
    "test_lift_rule": "lift 30 mm and check the cube rises with the gripper",
    "required_arms": 1,
    "semantic_ambiguity": 0.1,
}


def frames(*steps: int) -> str:
    return tool("expert.frame", steps=list(steps))


def learn(summary: Any = None) -> str:
    return tool("expert.learn", summary=SUMMARY if summary is None else summary)


@dataclass
class Session:
    result: LearningResult
    events: list[dict[str, Any]]
    bodies: list[bytes]

    def of_type(self, type_: str) -> list[dict[str, Any]]:
        return [e for e in self.events if e["type"] == type_]

    def tool_errors(self) -> list[str]:
        return [json.loads(e["result"]).get("error", "") for e in self.of_type("tool")]


async def _session(
    replies: list[str], cycle: bool, limits: LearningLimits | None, out_dir: Any
) -> Session:
    policy = ScriptedPolicy(replies, cycle=cycle)
    recorder = EpisodeRecorder(out_dir)
    async with LocalServer(policy=policy, capture_bodies=True) as server:
        endpoint = server.endpoint_config("m", "openai_chat", retry=FAST_RETRY)
        async with LLMPool([endpoint]) as llm:
            result = await learn_summary(
                FakeTask(), DEMO, llm, "m", recorder=recorder, limits=limits
            )
    recorder.close()
    assert server.bodies is not None
    return Session(result, recorder.events, [b for _, b in server.bodies])


def run(
    replies: list[str],
    *,
    cycle: bool = False,
    limits: LearningLimits | None = None,
    out_dir: Any = None,
) -> Session:
    return asyncio.run(_session(replies, cycle, limits, out_dir))


# -- the gate --------------------------------------------------------------------------------


def test_learn_after_two_frames_is_refused_then_accepted_after_three():
    s = run([tool("expert.retrieve"), frames(0, 6), learn(), frames(11), learn()])
    r = s.result
    assert (r.status, r.stop_reason) == ("learned", "learned"), r.error
    assert r.frames_inspected == [0, 6, 11]
    assert (r.model_calls, r.tool_calls, r.learn_refusals, r.invalid_outputs) == (5, 5, 1, 0)
    refusal = s.tool_errors()[2]
    assert "learning gate" in refusal and f"at least {MIN_DISTINCT_FRAMES} distinct" in refusal
    assert "inspected so far: 2 (0, 6)" in refusal
    # the refusal reaches the model in the next request
    assert "learning gate" in user_texts(body_json(s.bodies[3]))[-1]
    assert r.summary is not None and r.summary.grasp_region == SUMMARY["grasp_region"]
    assert len(s.of_type("learned")) == 1


def test_duplicate_frames_do_not_count_toward_the_gate():
    s = run([frames(2, 2, 3), frames(3, 2), learn(), frames(2, 4), learn()])
    r = s.result
    assert r.learned, r.error
    assert r.frames_inspected == [2, 3, 4]
    assert r.learn_refusals == 1
    assert "inspected so far: 2 (2, 3)" in s.tool_errors()[2]


def test_frames_are_sent_as_images_with_their_times():
    s = run([tool("expert.retrieve"), frames(0, 1, 2), learn()])
    index = json.loads(s.of_type("tool")[0]["result"])
    assert index["n_frames"] == N_FRAMES
    assert index["frames"][3] == {"frame": 3, "t_s": 1.0}
    assert set(index) == {"tool", "n_frames", "frames"}  # nothing but the index
    assert count_images(body_json(s.bodies[1])) == 0
    assert count_images(body_json(s.bodies[2])) == 3


def test_more_than_eight_frames_per_call_is_rejected():
    s = run([frames(*range(9)), frames(*range(8)), learn()])
    r = s.result
    assert r.learned, r.error
    (rejection,) = s.of_type("rejection")
    assert rejection["field"] == "args.steps"
    assert f"at most {P.MAX_EXPERT_FRAMES}" in rejection["message"]
    assert r.invalid_outputs == 1
    assert r.frames_inspected == list(range(8))


def test_out_of_range_frames_name_the_valid_range_and_show_nothing():
    s = run([frames(1, 2, N_FRAMES), frames(1, 2, 3), learn()])
    assert s.result.learned
    error = s.tool_errors()[0]
    assert f"no frame {N_FRAMES}" in error and f"valid frames: 0 to {N_FRAMES - 1}" in error
    assert s.of_type("tool")[0]["images"] == 0
    assert s.result.frames_inspected == [1, 2, 3]


def test_a_second_view_is_refused():
    s = run(
        [tool("expert.frame", step=1, view="topdown"), frames(1, 2, 3), learn()],
    )
    assert "one view, 'head'" in s.tool_errors()[0]


# -- the summary -------------------------------------------------------------------------------


def test_missing_required_fields_are_listed_all_at_once():
    partial = {"grasp_object_part": "the cube", "pre_close_checks": []}
    s = run([frames(0, 1, 2), learn(partial), learn()])
    assert s.result.learned
    error = s.tool_errors()[1]
    for name in REQUIRED_FIELDS:
        if name != "grasp_object_part":
            assert f"args.summary.{name}'" in error, name
    assert "args.summary.pre_close_checks': must hold at least 1" in error
    assert "learning gate" not in error


def test_gate_and_schema_problems_come_together():
    s = run([frames(0), learn({"grasp_region": ""}), frames(1, 2), learn()])
    error = s.tool_errors()[1]
    assert "learning gate" in error and "args.summary.grasp_region': must not be empty" in error


def test_summary_schema_limits_and_shapes():
    ok = parse_summary(json.dumps(SUMMARY))  # a JSON string is decoded
    assert ok.required_arms == 1
    cases = {
        "grasp_region": ("x" * (MAX_TEXT_CHARS + 1), "at most 500 characters"),
        "pre_close_checks": (["c"] * (MAX_LIST_ITEMS + 1), "at most 10 items"),
        "required_arms": (True, "must be 1 or 2"),
        "semantic_ambiguity": (1.5, "between 0 and 1"),
        "avoid_roles": (3, "must be a string or a list of strings"),
        "arm_assignment": ({"middle": "x"}, "must be 'left' or 'right'"),
        "smuggled": ("text", "unknown field; valid fields: grasp_object_part"),
    }
    for name, (value, message) in cases.items():
        with pytest.raises(P.DecisionError) as err:
            parse_summary({**SUMMARY, name: value})
        assert message in str(err.value), (name, str(err.value))
        assert f"args.summary.{name}" in str(err.value)
    with pytest.raises(P.DecisionError, match="not free text"):
        parse_summary("grasp the cube from the side")


def test_summary_text_holds_only_numbers_the_model_wrote():
    s = run([frames(0, 5, 9), learn()])
    text = s.result.summary_text
    assert text is not None and text == summary_text(parse_summary(SUMMARY))
    written = set(re.findall(r"\d+(?:\.\d+)?", json.dumps(SUMMARY)))
    assert set(re.findall(r"\d+(?:\.\d+)?", text)) <= written
    for name, value in SUMMARY.items():
        assert f"- {name}: " in text
        assert str(value if not isinstance(value, list) else value[0]) in text


# -- the stage and its budgets ------------------------------------------------------------------


def test_robot_and_camera_actions_are_rejected_in_the_learning_stage():
    move = reply({"action": "gripper.move_world", "axis": "z", "sign": "+", "distance_mm": 10})
    s = run([move, reply({"action": "camera.zoom_in"}), frames(0, 1, 2), learn()])
    assert s.result.learned
    rejections = s.of_type("rejection")
    assert len(rejections) == 2
    assert all("no actions in the learning stage" in e["message"] for e in rejections)
    # an evaluation-only tool is not offered here
    s = run([tool("geometry.verify"), frames(0, 1, 2), learn()])
    assert "not available in this episode" in s.of_type("rejection")[0]["message"]


def test_model_call_budget_ends_with_a_clear_failure(tmp_path):
    s = run([frames(0)], cycle=True, limits=LearningLimits(max_model_calls=4), out_dir=tmp_path)
    r = s.result
    assert (r.status, r.stop_reason, r.summary) == ("failed", "budget_exhausted", None)
    assert r.model_calls == 4 and "4 model calls without an accepted summary" in (r.error or "")
    assert read_result(tmp_path / "learning.json") == r
    assert s.events[-1]["type"] == "learning_end"


def test_three_invalid_replies_in_a_row_end_the_session():
    s = run(["no json here", "{", reply({"stop": False})], limits=LearningLimits())
    r = s.result
    assert (r.status, r.stop_reason, r.invalid_outputs) == ("failed", "invalid_output", 3)
    assert r.model_calls == 3


def test_stop_ends_the_session_without_a_summary():
    s = run([frames(0, 1, 2), reply({"stop": True})])
    assert (s.result.status, s.result.stop_reason) == ("failed", "model_stop")


def test_records_and_determinism(tmp_path):
    script = [tool("expert.retrieve"), frames(0, 3), learn(), frames(7), learn()]
    a = run(script, out_dir=tmp_path / "a")
    b = run(script, out_dir=tmp_path / "b")
    assert a.result.model_dump(exclude={"wall_s"}) == b.result.model_dump(exclude={"wall_s"})
    assert a.bodies == b.bodies
    stored = read_result(tmp_path / "a" / "learning.json")
    assert stored.summary == a.result.summary
    types = [e["type"] for e in a.events]
    assert types[0] == "learning_start" and types[-1] == "learning_end"
    assert {"request", "reply", "tool", "learned"} <= set(types)


def test_learning_prompt_states_the_stage_the_tools_the_gate_and_the_fields():
    prompt = learning_prompt(("left", "right"), 3.0)
    assert "two robot arms" in prompt and "about 3 frames per second" in prompt
    for name in (*P.DEMONSTRATION_TOOLS, *DemoSummary.model_fields):
        assert name in prompt, name
    assert f"at least {MIN_DISTINCT_FRAMES} distinct frames" in prompt
    assert "no robot or camera actions" in prompt
    assert "geometry.verify" not in prompt and "camera.view" not in prompt
    s = run([tool("expert.frame", step=N_FRAMES), frames(0, 1, 2), learn()])
    assert s.tool_errors()[0].startswith("args.step: no frame")
    body = body_json(s.bodies[0])
    assert "Pick up the red cube" in user_texts(body)[0]
    assert f"frame 0 to frame {N_FRAMES - 1}" in user_texts(body)[0]


def test_demo_frames_validate():
    with pytest.raises(ValueError, match="frames"):
        DemoFrames([], fps=3)
    with pytest.raises(ValueError, match="fps"):
        DemoFrames([jpeg(0)], fps=0)
    with pytest.raises(ValueError, match=r"frames\[1\]"):
        DemoFrames([jpeg(0), b""], fps=3)


# -- replies as real models write them (agent.replies) -------------------------------------------


def test_refusals_end_a_session_refused_with_repairs_that_name_them():
    refusal: Any = {"text": "I won't.", "finish_reason": "refusal"}
    s = run([refusal, refusal, refusal])
    r = s.result
    assert (r.status, r.stop_reason, r.invalid_outputs) == ("failed", "refused", 3)
    assert [e["kind"] for e in s.of_type("rejection")] == ["refusal"] * 3
    assert "your reply was a refusal (I won't.)" in user_texts(body_json(s.bodies[1]))[-1]


def test_reasoning_only_then_the_answer_in_the_reply_goes_on():
    thought: Any = {
        "body": {
            "id": "c",
            "model": "m",
            "choices": [
                {
                    "index": 0,
                    "message": {"content": None, "reasoning": tool("expert.retrieve")},
                    "finish_reason": "stop",
                }
            ],
        }
    }
    s = run([thought, tool("expert.retrieve"), frames(0, 5, 11), learn()])
    assert s.result.learned and s.result.invalid_outputs == 1
    assert s.of_type("rejection")[0]["kind"] == "reasoning_only"


class _ContextTooSmall:
    async def respond(self, request: Any) -> str:
        from vabench.llm_pool.policies import PolicyError

        raise PolicyError("prompt is too long: 210000 tokens > 200000 maximum", status=400)


def test_a_context_rejection_ends_a_session_context_exceeded_not_a_stopped_sweep():
    async def go() -> LearningResult:
        async with LocalServer(policy=_ContextTooSmall()) as server:
            endpoint = server.endpoint_config("m", "anthropic", retry=FAST_RETRY)
            async with LLMPool([endpoint]) as llm:
                return await learn_summary(FakeTask(), DEMO, llm, "m")

    r = asyncio.run(go())
    assert (r.status, r.stop_reason) == ("failed", "context_exceeded")
    assert r.error is not None and "prompt is too long" in r.error
