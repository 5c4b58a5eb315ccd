"""Evidence hints and the `rubric_judge` stand-in on hand-built trajectories with known
answers: a planner rejection, a repeated or changed action after it, a drop and a close far
from every object seen in the evaluator-only poses, a camera move before the first approach."""

from __future__ import annotations

import asyncio

from vabench.diagnostics.hints import RULES, hints
from vabench.diagnostics.judge import JUDGE_MARK
from vabench.diagnostics.judge_policy import RubricJudge
from vabench.llm_pool import ChatRequest, Turn
from vabench.llm_pool.apis.base import IncomingRequest


def action(step, label, ok=True, z=0.76, gc=(0.2, -0.1, 0.95)):
    return {
        "type": "action",
        "step": step,
        "label": label,
        "valid": True,
        "planner_success": ok,
        "clipped": {"right": False},
        "proprio": {"right": {"finger_center_xyz": list(gc), "is_open": "close" not in label}},
        "objects": {"cube": {"pos": [0.2, -0.1, z], "quat": [1, 0, 0, 0]}},
    }


RESET = {"type": "reset", "objects": {"cube": {"pos": [0.2, -0.1, 0.76], "quat": [1, 0, 0, 0]}}}


def found(events, protocol="active"):
    return {(h.item, h.step, h.source) for h in hints(events, protocol)}


def test_failure_hints_and_what_followed():
    events = [
        RESET,
        {"type": "camera", "step": 1, "label": "camera.view_side"},
        action(2, "move_world z-90mm", ok=False),
        action(3, "move_world z-90mm", ok=False),
        action(4, "move_world z-40mm"),
    ]
    got = found(events)
    assert ("AE", 1, "visible") in got  # a camera action before the first robot action
    assert ("gate_error", 2, "visible") in got and ("gate_error", 3, "visible") in got
    texts = {(h.item, h.step): h.text for h in hints(events, "active")}
    assert texts[("PF", 3)] == "repeated the failed action unchanged"
    assert texts[("PF", 4)].startswith("changed the action after the failure")


def test_drop_and_miss_from_evaluator_poses():
    events = [
        RESET,
        action(1, "gripper.close", gc=(0.2, -0.1, 0.77)),
        action(2, "move_world z+50mm", z=0.81),
        action(3, "move_world x+20mm", z=0.76),
        action(4, "gripper.close", gc=(0.4, 0.1, 0.95)),
    ]
    got = found(events)
    assert ("gate_error", 3, "evaluator") in got  # raised 50 mm, then back on the table
    assert ("gate_error", 4, "evaluator") in got  # closed ~37 cm from the cube
    assert ("gate_error", 1, "evaluator") not in got  # closed at the cube: no miss
    assert ("AE", 0, "visible") in got  # no camera action at all


def test_camera_hints_only_where_the_camera_can_move():
    """A passive episode's model gets five fixed views and no camera action: no hint about
    camera actions (AE's, ED's look after a failure); the others apply to both protocols."""
    events = [RESET, action(1, "move_world z-90mm", ok=False), action(2, "gripper.close")]
    active, passive = found(events, "active"), found(events, "passive")
    assert ("AE", 0, "visible") in active  # no camera action at all: worth a look
    assert not {h for h in passive if h[0] == "AE"}
    assert active - passive == {("AE", 0, "visible")}
    assert ("gate_error", 1, "visible") in passive and ("PF", 2, "visible") in passive
    looked = [*events[:2], {"type": "camera", "step": 2, "label": "camera.view_side"}]
    assert ("ED", 1, "visible") in found(looked) and ("ED", 1, "visible") not in found(
        looked, "passive"
    )
    for rule in RULES:
        assert rule.protocols and rule.protocols <= {"active", "passive"}, rule.name


def ask(transcript, question, annotator="judge-x-1", flip=0.0):
    request = IncomingRequest(
        "openai_chat",
        "x",
        ChatRequest(
            (Turn.user(f"Annotator: {annotator}\n\n{transcript}", question),),
            system=JUDGE_MARK + "\nrubric",
        ),
    )
    return asyncio.run(RubricJudge(flip=flip).respond(request))


TRANSCRIPT = """Task instruction: Pick up the red cube
Step 1 (view center_high)
  decision: camera camera.view_side
  camera moved: now showing side
Step 2 (view side)
  decision: robot move_world z-90mm (reason: down)
  executed: valid yes, planner rejected
Step 3 (view side)
  decision: robot move_world z-40mm (reason: less)
  executed: valid yes, planner ok
Step 4 (view side)
  decision: robot gripper.close
  executed: valid yes, planner ok
End: the step budget ran out after 4 of 4 steps."""


def test_rubric_judge_rules_without_noise():
    assert '{"gate_error": 1, "gate_ambiguity": 1}' in ask(TRANSCRIPT, "Stage one: gates.")
    reply = ask(TRANSCRIPT, "Stage two: ... Judge these criteria: TL, AE, FG, ED, PF.")
    assert '{"TL": 1, "AE": 1, "FG": 1, "ED": 1, "PF": 1}' in reply


def test_rubric_judge_noise_is_seeded_per_judge():
    replies = {
        a: ask(TRANSCRIPT, "Stage two: Judge these criteria: TL, AE, SR, MS, MP, FG.", a, flip=0.5)
        for a in ("judge-x-1", "judge-x-2", "judge-x-3")
    }
    assert len(set(replies.values())) > 1
    assert replies["judge-x-1"] == ask(
        TRANSCRIPT,
        "Stage two: Judge these criteria: TL, AE, SR, MS, MP, FG.",
        "judge-x-1",
        flip=0.5,
    )
