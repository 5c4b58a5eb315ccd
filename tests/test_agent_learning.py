"""The learning stage (PROTOCOL_FACTS 6): the demonstration tools, the learning gate, the
`expert.learn` fields and their checks, the summary as observations show it, the records and
the session's budgets.

Sessions run against the embedded server's scripted policy over real HTTP (as the engine tests
do), on synthetic demonstrations of solid-colour JPEG frames: the session never looks inside a
frame, so no simulator or renderer is needed.
"""

from __future__ import annotations

import asyncio
import base64
import io
import json
import re
from dataclasses import dataclass
from typing import Any

import pytest
from engine_util import FAST_RETRY, body_json, count_images, reply, tool, user_texts
from PIL import Image as PILImage
from pydantic import ValidationError

from vabench import protocol as P
from vabench.agent.demonstration import (
    MIN_DISTINCT_FRAMES,
    DemoFrames,
    DemoScene,
    learning_prompt,
)
from vabench.agent.learning import (
    LEARNING_VERSION,
    LearningLimits,
    LearningResult,
    learn_summary,
    read_result,
)
from vabench.agent.observation import ActionFeedback, observation_text
from vabench.agent.records import EpisodeRecorder
from vabench.agent.summary import (
    AFFORDANCE_ENUMS,
    AFFORDANCE_FLAGS,
    CHECKED_FIELDS,
    FREE_FIELDS,
    REQUIRED_FIELDS,
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
BASKET = DemoFrames(
    [jpeg(i) for i in range(N_FRAMES)],
    fps=3.0,
    label="atomic",
    videos=[(0, "Place the cube."), (4, "Grasp the bottle."), (8, "Grasp the pen.")],
)

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
    """expert.learn with the summary fields at the top level of args (the reference's shape)."""
    return tool("expert.learn", **(SUMMARY if summary is None else summary))


RETRIEVE = tool("expert.retrieve")


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
    replies: list[str],
    cycle: bool,
    limits: LearningLimits | None,
    out_dir: Any,
    demo: DemoFrames,
    task: FakeTask,
) -> Session:
    policy = ScriptedPolicy(replies, cycle=cycle)
    recorder = EpisodeRecorder(out_dir)
    async with LocalServer(policy=policy, capture_bodies=True) as server:
        endpoint = server.endpoint_config("m", "openai_chat", retry=FAST_RETRY)
        async with LLMPool([endpoint]) as llm:
            result = await learn_summary(task, demo, llm, "m", recorder=recorder, limits=limits)
    recorder.close()
    assert server.bodies is not None
    return Session(result, recorder.events, [b for _, b in server.bodies])


def run(
    replies: list[str],
    *,
    cycle: bool = False,
    limits: LearningLimits | None = None,
    out_dir: Any = None,
    demo: DemoFrames = DEMO,
    task: FakeTask = FakeTask(),
) -> Session:
    return asyncio.run(_session(replies, cycle, limits, out_dir, demo, task))


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
    assert r.summary == SUMMARY
    assert len(s.of_type("learned")) == 1


def test_learn_before_expert_retrieve_is_refused():
    s = run([frames(0, 5, 9), learn(), RETRIEVE, learn()])
    r = s.result
    assert r.learned, r.error
    assert (r.learn_refusals, r.invalid_outputs) == (1, 0)
    refusal = s.tool_errors()[1]
    assert "call expert.retrieve before expert.learn" in refusal
    assert "distinct" not in refusal  # the three frames were enough


def test_duplicate_frames_do_not_count_toward_the_gate():
    s = run([RETRIEVE, frames(2, 2, 3), frames(3, 2), learn(), frames(2, 4), learn()])
    r = s.result
    assert r.learned, r.error
    assert r.frames_inspected == [2, 3, 4]
    assert r.learn_refusals == 1
    assert "inspected so far: 2 (2, 3)" in s.tool_errors()[3]


def test_several_videos_need_three_frames_of_each():
    script = [RETRIEVE, frames(0, 1, 2, 3, 4, 5), learn(BASKET_SUMMARY), frames(8, 9, 10, 6)]
    s = run([*script, learn(BASKET_SUMMARY)], demo=BASKET)
    r = s.result
    assert r.learned, r.error
    refusal = s.tool_errors()[2]
    assert f"at least {MIN_DISTINCT_FRAMES} distinct frames of every video" in refusal
    assert "video 2 (2), video 3 (0)" in refusal and "video 1" not in refusal


def test_frames_are_sent_as_images_with_their_times():
    s = run([tool("expert.retrieve"), frames(0, 1, 2), learn()])
    index = json.loads(s.of_type("tool")[0]["result"])
    assert index["n_frames"] == N_FRAMES
    assert index["frames"][3] == {"frame": 3, "t_s": 1.0}
    assert set(index) == {"tool", "n_frames", "frames"}  # nothing but the index
    assert count_images(body_json(s.bodies[1])) == 0
    assert count_images(body_json(s.bodies[2])) == 3


def test_more_than_eight_frames_per_call_is_rejected():
    s = run([RETRIEVE, frames(*range(9)), frames(*range(8)), learn()])
    r = s.result
    assert r.learned, r.error
    (rejection,) = s.of_type("rejection")
    assert rejection["field"] == "args.steps"
    assert f"at most {P.MAX_EXPERT_FRAMES}" in rejection["message"]
    assert r.invalid_outputs == 1
    assert r.frames_inspected == list(range(8))


def test_out_of_range_frames_name_the_valid_range_and_show_nothing():
    s = run([RETRIEVE, frames(1, 2, N_FRAMES), frames(1, 2, 3), learn()])
    assert s.result.learned
    error = s.tool_errors()[1]
    assert f"no frame {N_FRAMES}" in error and f"valid frames: 0 to {N_FRAMES - 1}" in error
    assert s.of_type("tool")[1]["images"] == 0
    assert s.result.frames_inspected == [1, 2, 3]


def test_a_second_view_is_refused():
    s = run(
        [tool("expert.frame", step=1, view="topdown"), RETRIEVE, frames(1, 2, 3), learn()],
    )
    assert "one view, 'head'" in s.tool_errors()[0]


# -- the summary -------------------------------------------------------------------------------


BASKET_SUMMARY: dict[str, Any] = {
    **SUMMARY,
    "object_strategies": {"cube": "top grasp", "pen": "grasp the middle of the shaft"},
    "release_or_completion_rule": "done when all five objects rest in the basket",
}


def test_fields_at_the_top_level_are_kept_whole_with_extras_and_no_length_limits():
    summary = {
        **SUMMARY,
        "grasp_region": "x" * 3000,
        "pre_close_checks": [f"check {i}" for i in range(25)],
        "arm_assignment": {"right": "grasps", "left": "waits"},
        "object_strategies": {"cube": ["top grasp", "release low"]},
        "my_own_note": {"nested": [1, 2, {"k": True}]},
        "summary_model": "someone else",
    }
    s = run([RETRIEVE, frames(0, 5, 9), learn(summary)])
    r = s.result
    assert r.learned, r.error
    kept = {k: v for k, v in summary.items() if k != "summary_model"}
    assert r.summary == kept
    assert r.summary_text == json.dumps(kept, indent=2, ensure_ascii=False)
    assert "someone else" not in (r.summary_text or "")
    assert s.of_type("learned")[0]["summary"] == kept


def test_the_summary_wrapper_is_read_as_the_same_call():
    s = run([RETRIEVE, frames(0, 5, 9), tool("expert.learn", summary=SUMMARY)])
    assert s.result.learned and s.result.summary == SUMMARY
    assert parse_summary({"summary": json.dumps(SUMMARY)}) == SUMMARY
    with pytest.raises(P.DecisionError, match=r"args\.summary': must be a JSON object"):
        parse_summary({"summary": "grasp the cube from the side"})
    # a summary field next to other fields is no wrapper: it is one more field
    assert parse_summary({**SUMMARY, "summary": "short"})["summary"] == "short"


def test_missing_required_fields_are_listed_all_at_once_as_a_tool_error():
    partial = {"grasp_object_part": "the cube", "pre_close_checks": []}
    s = run([RETRIEVE, frames(0, 1, 2), learn(partial), tool("expert.learn"), learn()])
    r = s.result
    assert r.learned
    assert (r.learn_refusals, r.invalid_outputs) == (2, 0)  # calls spent, no repair
    error = s.tool_errors()[2]
    for name in REQUIRED_FIELDS:
        if name not in ("grasp_object_part", "pre_close_checks"):
            assert f"'args.{name}': required, not empty" in error, name
    assert "'args.pre_close_checks': required, not empty, got []" in error
    assert "learning gate" not in error
    assert all(f"'args.{name}'" in s.tool_errors()[3] for name in REQUIRED_FIELDS)


def test_gate_and_field_problems_come_together():
    s = run([frames(0), learn({**SUMMARY, "grasp_region": " "}), RETRIEVE, frames(1, 2), learn()])
    error = s.tool_errors()[1]
    assert "call expert.retrieve" in error and "inspected so far: 1 (0)" in error
    assert "'args.grasp_region': required, not empty" in error


def test_field_checks():
    profile = {
        "part_shape": "box",
        "symmetry_class": "four_fold",
        "centering_tolerance": "moderate",
        "vertical_tolerance": "permissive",
        "avoid_ends": False,
        "requires_bilateral_contact": True,
        "requires_dual_arm": False,
    }
    ok = {
        **SUMMARY,
        "grasp_region": ["the side faces"],  # any non-empty value, as the reference takes it
        "task_stage": "initial_grasp",
        "post_grasp_goal": "lift",
        "functional_constraints": [],
        "required_arms": 2,
        "semantic_ambiguity": 0,
        "affordance_profile": profile,
        "avoid_roles": 3,  # free fields are not checked
    }
    assert parse_summary(ok) == ok
    cases: dict[str, tuple[Any, str]] = {
        "test_lift_rule": (None, "'args.test_lift_rule': required, not empty, got null"),
        "grasp_region": ({}, "'args.grasp_region': required, not empty"),
        "pre_close_checks": ("look", "'args.pre_close_checks': must be a list"),
        "task_stage": ("", "'args.task_stage': must be a non-empty string"),
        "post_grasp_goal": (["lift"], "'args.post_grasp_goal': must be a non-empty string"),
        "functional_constraints": ("upright", "'args.functional_constraints': must be a list"),
        "required_arms": (True, "'args.required_arms': must be 1 or 2, got true"),
        "semantic_ambiguity": (1.5, "'args.semantic_ambiguity': must be a number from 0 to 1"),
        "affordance_profile": ("box", "'args.affordance_profile': must be an object"),
    }
    for name, (value, message) in cases.items():
        with pytest.raises(P.DecisionError) as err:
            parse_summary({**SUMMARY, name: value})
        assert message in str(err.value), (name, str(err.value))
    for value in (3, "1", 0):
        with pytest.raises(P.DecisionError, match="must be 1 or 2"):
            parse_summary({**SUMMARY, "required_arms": value})
    for value in (True, "0.5", -0.1, float("nan")):
        with pytest.raises(P.DecisionError, match="must be a number from 0 to 1"):
            parse_summary({**SUMMARY, "semantic_ambiguity": value})
    with pytest.raises(P.DecisionError) as err:
        parse_summary({**SUMMARY, "pre_close_checks": ["ok", " "], "functional_constraints": [1]})
    assert "'args.pre_close_checks[1]'" in str(err.value)
    assert "'args.functional_constraints[0]'" in str(err.value)
    bad_profile = {**profile, "part_shape": "sphere", "avoid_ends": "yes"}
    del bad_profile["requires_dual_arm"], bad_profile["symmetry_class"]
    with pytest.raises(P.DecisionError) as err:
        parse_summary({**SUMMARY, "affordance_profile": bad_profile})
    text = str(err.value)
    assert "'args.affordance_profile.part_shape': must be one of unknown, slender_cylinder" in text
    assert "'args.affordance_profile.symmetry_class': required: one of" in text
    assert "'args.affordance_profile.avoid_ends': must be true or false" in text
    assert "'args.affordance_profile.requires_dual_arm': required: true or false" in text


def test_the_basket_refuses_counts_per_type_and_lettered_objects():
    assert parse_summary(BASKET_SUMMARY, composite=True) == BASKET_SUMMARY
    for text, found in [
        ("place the two cubes first", "two cubes"),
        ("then 1 pen", "1 pen"),
        ("four visually distinct bottles", "four visually distinct bottles"),
        ("grasp cube B before bottle A", "cube B"),
    ]:
        summary = {**BASKET_SUMMARY, "safety_notes": [text]}
        assert parse_summary(summary) == summary  # one video: no such rule
        with pytest.raises(P.DecisionError) as err:
            parse_summary(summary, composite=True)
        assert f'found "{found}"' in str(err.value), text
    # counted in a key as well, and listed with the other problems
    with pytest.raises(P.DecisionError) as err:
        parse_summary({**BASKET_SUMMARY, "two pens": "x", "grasp_region": ""}, composite=True)
    assert '"two pens"' in str(err.value) and "'args.grasp_region'" in str(err.value)
    s = run(
        [
            RETRIEVE,
            frames(0, 1, 2, 4, 5, 6, 8, 9),
            frames(10),
            learn({**BASKET_SUMMARY, "grasp_object_part": "cube A"}),
            learn(BASKET_SUMMARY),
        ],
        demo=BASKET,
    )
    assert s.result.learned and s.result.learn_refusals == 1
    assert 'found "cube A"' in s.tool_errors()[3]


def test_the_summary_sits_last_in_an_evaluation_observation_as_json():
    s = run([RETRIEVE, frames(0, 5, 9), learn()])
    shown = s.result.summary_text
    assert shown is not None
    arm = {
        "is_open": True,
        "finger_center_xyz": [0.1, -0.2, 0.9],
        "control_eepose_xyz": [0.1, -0.2, 1.0],
        "control_eepose_rpy_deg": [180.0, 0.0, 90.0],
        "control_eepose_quat": [0.0, 0.7071, 0.7071, 0.0],
        "local_axes_world": {"rx": [0.0, 0.0, -1.0], "ry": [1.0, 0.0, 0.0], "rz": [0.0, 1.0, 0.0]},
    }
    text = observation_text(
        step=1,
        step_budget=5,
        instruction=FakeTask.instruction,
        proprio={"right": arm},
        arms=("right",),
        feedback=ActionFeedback(),
        executed_actions=[],
        demonstration_summary=shown,
        available_actions=['{"stop": true}'],
    )
    one_command = text.index("Reply with exactly one JSON command.")
    heading = text.index("Demonstration summary (saved for this run; keep it as additive")
    assert text.index('{"stop": true}') < one_command < heading
    assert text.endswith(shown)
    assert json.loads(text[heading:].split("\n", 1)[1]) == SUMMARY
    # every number in it is one the model wrote
    written = set(re.findall(r"\d+(?:\.\d+)?", json.dumps(SUMMARY)))
    assert set(re.findall(r"\d+(?:\.\d+)?", shown)) <= written
    assert summary_text(SUMMARY) == shown


# -- records -------------------------------------------------------------------------------------


V1_RECORD: dict[str, Any] = {
    "v": 1,
    "task": "grasp_single_cube",
    "model": "m",
    "label": "grasp_single_cube",
    "status": "learned",
    "stop_reason": "learned",
    "error": None,
    "summary": {**SUMMARY, "task_stage": None, "safety_notes": None},
    "summary_text": "learned from the task's demonstration video.\n- grasp_object_part: x",
    "n_frames": 31,
    "frames_inspected": [0, 15, 30],
    "model_calls": 3,
    "tool_calls": 3,
    "invalid_outputs": 0,
    "learn_refusals": 0,
    "tokens": {"input": 10, "cached_input": 0, "cache_write": 0, "output": 5, "reasoning": 0},
    "cost_usd": 0.0,
    "wall_s": 1.0,
}


def test_older_records_read_and_unknown_versions_are_refused_by_name(tmp_path):
    path = tmp_path / "learning.json"
    path.write_text(json.dumps(V1_RECORD))
    old = read_result(path)
    assert (old.v, old.attempt, old.earlier_attempts, old.scene) == (LEARNING_VERSION, 1, [], False)
    assert old.summary == SUMMARY  # the nulls of unset fields dropped
    assert old.summary_text == V1_RECORD["summary_text"]  # shown as it was
    path.write_text(json.dumps({**V1_RECORD, "v": 7}))
    with pytest.raises(ValidationError) as err:
        read_result(path)
    assert "a learning record of version 7; this vabench reads versions 1, 2" in str(err.value)
    assert err.value.errors()[0]["loc"] == ("v",)


# -- the stage and its budgets ------------------------------------------------------------------


def test_robot_and_camera_actions_are_rejected_in_the_learning_stage():
    move = reply({"action": "gripper.move_world", "axis": "z", "sign": "+", "distance_mm": 10})
    s = run([move, reply({"action": "camera.zoom_in"}), RETRIEVE, frames(0, 1, 2), learn()])
    assert s.result.learned
    rejections = s.of_type("rejection")
    assert len(rejections) == 2
    assert all("no actions in the learning stage" in e["message"] for e in rejections)
    # an evaluation-only tool is not offered here
    s = run([tool("geometry.verify"), RETRIEVE, frames(0, 1, 2), learn()])
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
    s = run([RETRIEVE, frames(0, 1, 2), reply({"stop": True})])
    assert (s.result.status, s.result.stop_reason) == ("failed", "model_stop")


def test_records_and_determinism(tmp_path):
    script = [RETRIEVE, frames(0, 3), learn(), frames(7), learn()]
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
    for name in (*P.DEMONSTRATION_TOOLS, *REQUIRED_FIELDS, *CHECKED_FIELDS, *FREE_FIELDS):
        assert name in prompt, name
    for name, values in AFFORDANCE_ENUMS.items():
        assert f"{name} (one of {', '.join(values)})" in prompt
    assert all(flag in prompt for flag in AFFORDANCE_FLAGS)
    assert f"at least {MIN_DISTINCT_FRAMES} distinct frames were shown" in prompt
    assert '"expert.retrieve", "args": {}} first' in prompt
    assert "its fields directly in args" in prompt
    assert "do not invent metric coordinates" in prompt
    assert "which arm does what" in prompt  # two arms: roles, phases, joint moves
    assert "no robot or camera actions" in prompt
    assert "geometry.verify" not in prompt and "camera.view" not in prompt
    assert "which arm does what, the phases" not in learning_prompt(("right",), 3.0)
    assert "scene the video starts from" not in prompt
    assert "scene the video starts from" in learning_prompt(("right",), 3.0, scene=True)
    basket = learning_prompt(("right",), 3.0, 4)
    assert "4 RGB videos" in basket and "of every video" in basket
    assert "object_strategies" in basket and "all five placements" in basket
    assert '"cube A"' in basket and "object_strategies, an object" not in prompt
    s = run([tool("expert.frame", step=N_FRAMES), RETRIEVE, frames(0, 1, 2), learn()])
    assert s.tool_errors()[0].startswith("args.step: no frame")
    body = body_json(s.bodies[0])
    assert "Pick up the red cube" in user_texts(body)[0]
    assert f"frame 0 to frame {N_FRAMES - 1}" in user_texts(body)[0]
    assert count_images(body) == 0  # no scene given: none shown


def test_a_scene_is_the_first_message_with_its_image():
    scene = DemoScene("Observation step: 1\nTask instruction: Pick up the red cube.", jpeg(99))
    demo = DemoFrames(DEMO.frames, DEMO.fps, "demo-a", scene=scene)
    s = run([RETRIEVE, frames(0, 5, 9), learn()], demo=demo)
    assert s.result.learned and s.result.scene
    first = body_json(s.bodies[0])
    assert count_images(first) == 1
    (text,) = user_texts(first)
    assert scene.text in text and f"frame 0 to frame {N_FRAMES - 1}" in text
    assert "scene the video starts from" in first["messages"][0]["content"]
    url = first["messages"][1]["content"][-1]["image_url"]["url"]
    assert base64.b64decode(url.split(",", 1)[1]) == scene.image
    assert s.of_type("learning_start")[0]["scene"] is True
    with pytest.raises(ValueError, match="several videos"):
        DemoFrames(BASKET.frames, 3.0, videos=BASKET.videos, scene=scene)


def test_the_basket_learns_without_a_scene():
    s = run(
        [RETRIEVE, frames(0, 1, 2, 4, 5, 6, 8, 9), frames(10), learn(BASKET_SUMMARY)], demo=BASKET
    )
    assert s.result.learned and not s.result.scene
    first = body_json(s.bodies[0])
    assert count_images(first) == 0
    (text,) = user_texts(first)
    assert "Observation step" not in text and "No scene of this task is shown" in text
    assert "- video 2, frames 4 to 7: Grasp the bottle." in text


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
    s = run([thought, RETRIEVE, frames(0, 5, 11), learn()])
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
