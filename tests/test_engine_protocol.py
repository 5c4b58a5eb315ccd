"""The decision protocol through the engine (FACTS "Model-facing protocol"): each decision form
reaches the right place and each budget ends the episode the way the spec says.

Every test runs a real episode (C MuJoCo, tiny images, the embedded server over HTTP) under a
scripted policy whose probes record the simulator while the model is being asked, so "a camera
action changes no physics" is checked on the batch itself, bit for bit.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from engine_util import (
    STOP,
    body_json,
    camera,
    count_images,
    move,
    reply,
    robot_state,
    run_scripted,
    tool,
    user_messages,
    user_texts,
)

from vabench import protocol as P
from vabench.render.worker import RenderPool
from vabench.tasks import get_task
from vabench.tasks.task_batch import TaskBatch, run_experts

TASK = "grasp_single_cube"
SEED = 1000


@pytest.fixture(scope="module")
def pool():
    with RenderPool(workers=1, timeout_s=60) as p:
        yield p


def test_each_decision_form_reaches_the_right_place(pool):
    run = run_scripted(
        TASK,
        [
            camera("view_side"),  # step 1
            camera("zoom_in"),  # step 2
            tool("geometry.verify"),  # still step 3
            tool("camera.history", step=1),  # still step 3
            move("z", "+", 20),  # step 3
            STOP,  # step 4
        ],
        pool,
        seed=SEED,
        budget=6,
    )
    r, probes = run.result, run.probes
    assert (r.status, r.stop_reason) == ("failure", "model_stop"), r.error
    assert (r.steps_used, r.camera_actions, r.robot_actions, r.tool_calls) == (3, 2, 1, 2)
    assert len(probes) == 6

    # camera actions (requests 0 -> 1 -> 2): a new camera, no simulator call, physics untouched
    for before, after in ((probes[0], probes[1]), (probes[1], probes[2])):
        assert after.step_calls == before.step_calls == 0
        assert np.array_equal(after.qpos, before.qpos)
        assert not np.allclose(after.camera_pos, before.camera_pos)
    assert [e["view"] for e in run.of_type("camera")] == ["side", "side (adjusted)"]

    # tools (requests 2 -> 3 -> 4): no step, no simulator call, the answer in the thread
    for before, after in ((probes[2], probes[3]), (probes[3], probes[4])):
        assert after.step_calls == before.step_calls == 0
        assert np.array_equal(after.qpos, before.qpos)
        assert np.array_equal(after.camera_pos, before.camera_pos)
    texts = [user_texts(body_json(raw)) for _, raw in run.bodies]
    assert texts[3][-1].startswith('{"tool": "geometry.verify"')
    assert '"camera.history"' in texts[4][-1]
    # camera.history re-attached the step-1 image with its answer (the older copy of the same
    # image gives way to a placeholder: no image is sent twice)
    assert count_images(user_messages(body_json(run.bodies[4][1]))[-1]) == 1
    assert "[image from step 1 omitted]" in "\n".join(texts[4])

    # the robot action (requests 4 -> 5): one simulator call, the arm moved up 20 mm
    assert probes[5].step_calls == 1 and run.counters.actions == 1
    assert not np.array_equal(probes[5].qpos, probes[4].qpos)
    gc_before, gc_after = probes[4].gcs["right"], probes[5].gcs["right"]
    assert gc_after[2] - gc_before[2] == pytest.approx(0.020, abs=0.002)
    [action] = run.of_type("action")
    assert action["step"] == 3 and action["valid"] and action["planner_success"]

    # the observations the model saw: steps 1..4, the view each decision left behind
    obs = run.of_type("observation")
    assert [e["step"] for e in obs] == [1, 2, 3, 4]
    assert [e["view"] for e in obs] == ["center_high", "side", "side (adjusted)", "side (adjusted)"]
    robot = robot_state(texts[5][-1])["right"]
    assert (robot["last_action_valid"], robot["last_planner_success"]) == (True, True)


def _world_turn(axis: str, deg: float) -> np.ndarray:
    """The right-hand rotation by deg about world axis x|y|z (Rodrigues)."""
    k = np.eye(3)["xyz".index(axis)]
    skew = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * skew + (1.0 - np.cos(t)) * skew @ skew


def test_world_rotation_is_read_and_executed_never_offered(pool):
    """The reference's unadvertised world rotation, in its compact and its JSON form: both
    executed about the fixed world axis (the local axes the model sees turn by R(e, t)), GC
    held; no request offers it."""
    script = [
        reply({"action": "gripper.rotate_rz_ccw.20deg"}),
        reply({"action": "gripper.rotate_world", "axis": "x", "sign": "-", "angle_deg": 15}),
        STOP,
    ]
    run = run_scripted(TASK, script, pool, seed=SEED, budget=4)
    r = run.result
    assert (r.status, r.stop_reason) == ("failure", "model_stop"), r.error
    assert (r.robot_actions, r.invalid_outputs) == (2, 0)
    labels = [e["label"] for e in run.of_type("decision")]
    assert labels == ["rotate_world z+20deg", "rotate_world x-15deg", "stop"]
    assert all(a["valid"] and a["planner_success"] for a in run.of_type("action"))
    assert b"rotate_world" not in run.bodies[0][1]  # the system prompt and the first observation
    texts = [user_texts(body_json(raw)) for _, raw in run.bodies]
    axes = [robot_state(t[-1])["right"]["local_axes_world"] for t in texts]
    frames = [np.array([a[k] for k in ("rx", "ry", "rz")]).T for a in axes]
    for (axis, deg), r0, r1 in zip((("z", 20.0), ("x", -15.0)), frames, frames[1:], strict=False):
        np.testing.assert_allclose(_world_turn(axis, deg) @ r0, r1, atol=2e-3)  # 4 decimals shown
    assert len(run.probes) == 3
    for before, after in itertools.pairwise(run.probes):
        assert np.linalg.norm(after.gcs["right"] - before.gcs["right"]) < 5e-4


def test_three_invalid_replies_end_the_episode_after_two_repairs(pool):
    bad = [
        "no json at all",
        reply({"action": "gripper.move_world", "axis": "w", "sign": "+", "distance_mm": 10}),
        reply({"action": "gripper.teleport"}),
    ]
    run = run_scripted(TASK, bad, pool, seed=SEED, budget=5)
    r = run.result
    assert (r.status, r.stop_reason) == ("failure", "invalid_output")
    assert (r.invalid_outputs, r.model_calls, r.steps_used) == (3, 3, 0)
    rejections = run.of_type("rejection")
    assert [e["repair"] for e in rejections] == [1, 2, 3]
    assert rejections[1]["field"] == "axis"
    assert r.error == rejections[2]["message"]
    # each repair turn, text only: the current observation, then the error; the request
    # still holds the current image once, in the observation's turn
    for i in (1, 2):
        body = body_json(run.bodies[i][1])
        last = user_texts(body)[-1]
        assert rejections[i - 1]["message"] in last
        assert "Observation step: 1" in last
        assert robot_state(last)["right"]["is_open"] in (True, False)
        assert last.index("Observation step: 1") < last.index(rejections[i - 1]["message"])
        assert count_images(user_messages(body)[-1]) == 0
        assert count_images(body) == 1
    assert len(run.bodies) == 3


def test_a_sixth_camera_action_in_a_row_is_executed(pool):
    """The camera-chain limit is an instruction of the prompt (paper), not a rejection."""
    views = ["view_topdown", "view_side", "zoom_in", "zoom_out", "yaw_left"]
    script = [
        *(camera(v) for v in views),  # steps 1-5
        camera("view_front_side_45"),  # step 6: the sixth in a row, executed
        move("z", "+", 10),  # step 7
        STOP,
    ]
    run = run_scripted(TASK, script, pool, seed=SEED, budget=10)
    r = run.result
    assert (r.status, r.stop_reason) == ("failure", "model_stop"), r.error
    assert (r.camera_actions, r.robot_actions, r.invalid_outputs, r.steps_used) == (6, 1, 0, 7)
    assert run.of_type("rejection") == []
    assert run.of_type("camera")[-1]["view"] == "front_side_45"


def test_twenty_tool_calls_in_a_row_end_with_the_round_trip_limit(pool):
    script = [tool("geometry.verify")] * P.MAX_TOOL_ROUND_TRIPS
    run = run_scripted(TASK, script, pool, seed=SEED, budget=5)
    r = run.result
    assert (r.status, r.stop_reason) == ("failure", "round_trip_limit"), r.error
    assert (r.tool_calls, r.model_calls, r.steps_used) == (20, 20, 0)
    assert run.counters.step_calls == 0


def test_stop_ends_with_model_stop(pool):
    run = run_scripted(TASK, [STOP], pool, seed=SEED, budget=5)
    r = run.result
    assert (r.status, r.stop_reason, r.success, r.scored) == ("failure", "model_stop", False, True)
    assert (r.steps_used, r.model_calls, r.progress) == (0, 1, 0)


def test_budget_exhaustion(pool):
    run = run_scripted(TASK, [move("z", "+", 10), move("z", "-", 10)], pool, seed=SEED, budget=2)
    r = run.result
    assert (r.status, r.stop_reason, r.success) == ("failure", "budget_exhausted", False)
    assert (r.steps_used, r.step_budget, r.robot_actions, r.model_calls) == (2, 2, 2, 2)
    assert run.of_type("episode_start")[0]["step_budget"] == 2


def test_the_experts_actions_replayed_through_the_engine_succeed(pool):
    task = get_task(TASK)
    [expert] = run_experts(TaskBatch(task, 1, backend="c"), [SEED])
    assert expert.success, expert.end
    actions = [a["action"] for a in expert.actions]
    run = run_scripted(TASK, [reply(a) for a in actions], pool, seed=SEED, budget=None)
    r = run.result
    assert (r.status, r.stop_reason, r.success) == ("success", "success", True), r.error
    assert r.step_budget == task.step_budget
    assert (r.steps_used, r.robot_actions, r.model_calls) == (len(actions),) * 3
    assert r.checkpoints_reached == list(task.checkpoints)
    assert r.progress == r.n_checkpoints == len(task.checkpoints)
    # the engine's per-step progress is the expert's, step for step
    assert [e["progress"] for e in run.of_type("action")] == [a["progress"] for a in expert.actions]
    # stopped early (how the precompile runs only an expert's first actions): the same first
    # actions, then "stopped"
    [first] = run_experts(TaskBatch(task, 1, backend="c"), [SEED], max_steps=2)
    assert (first.success, first.end, first.steps) == (False, "stopped after 2 steps", 2)
    assert [a["action"] for a in first.actions] == actions[:2]


def test_dual_arm_forms_reach_their_arm_and_camera_target(pool):
    side = {"axis": "z", "sign": "+", "distance_mm": 10}
    script = [
        camera("view_left_side"),
        camera("view_both_topdown"),
        reply({"action": "camera.view_topdown", "arm": "left"}),  # rejected: "arm" on a camera
        reply({"action": "dual_gripper.move_world", "left": side, "right": side}),
        reply(
            {
                "action": "gripper.rotate_local",
                "axis": "rz",
                "sign": "-",
                "angle_deg": 10,
                "arm": "left",
            }
        ),
        reply({"action": "right_gripper.close"}),
        STOP,
    ]
    run = run_scripted("handover_horizontal_block", script, pool, budget=8)
    r = run.result
    assert (r.status, r.stop_reason) == ("failure", "model_stop"), r.error
    assert (r.camera_actions, r.robot_actions, r.invalid_outputs) == (2, 3, 1)
    assert [e["view"] for e in run.of_type("camera")] == ["left_side", "both_topdown"]
    assert run.of_type("rejection")[0]["field"] == "arm"
    labels = [e["label"] for e in run.of_type("decision")]
    assert labels[2:5] == [
        "dual_move_world left z+10mm right z+10mm",
        "rotate_local left rz-10deg",
        "right_gripper.close",
    ]
    assert run.counters.step_calls == 3
    # the dual move (requests 3 -> 4) lifted both grasp centres by its 10 mm
    p = run.probes
    for arm in ("left", "right"):
        assert p[4].gcs[arm][2] - p[3].gcs[arm][2] == pytest.approx(0.010, abs=0.002), arm
