"""The pen and bottle families: grasp_single_pen, grasp_single_bottle,
grasp_single_bottle_upright, grasp_pen_leaning_cube, place_single_bottle_upright.

The scene ranges and thresholds below are transcribed from the paper's tables
(tab:seed-spec-grasp, tab:seed-spec-place) and FACTS, independently of the modules' constants.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.expert_runs import expert_episodes
from tests.task_states import StateBuilder
from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import get_task
from vabench.tasks.task_batch import TaskBatch, run_experts

TABLE_Z = 0.741
SEEDS = range(1000, 1200)
EPS = 1e-9

GRASPS = {  # task: (object, x range, y range, yaw range deg or None for upright)
    "grasp_single_pen": ("pen", (0.18, 0.26), (-0.20, -0.10), (-30.0, 30.0)),
    "grasp_single_bottle": ("bottle", (0.20, 0.28), (-0.16, -0.04), (-22.5, 22.5)),
    "grasp_single_bottle_upright": ("bottle", (0.20, 0.28), (-0.16, -0.04), None),
    "grasp_pen_leaning_cube": ("pen", (0.16, 0.22), (-0.24, -0.20), (-15.0, 15.0)),
}
PEN_R, PEN_HALF_SEG = 0.007, 0.063
BOTTLE_FACE_R, BOTTLE_HALF_H = 0.032 * np.cos(np.pi / 16), 0.06


def _mat(quat: np.ndarray) -> np.ndarray:
    """Rotation matrix of a wxyz quaternion, in float64 numpy (independent of the package)."""
    w, x, y, z = np.asarray(quat, float) / np.linalg.norm(quat)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _heading(v: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(v[1], v[0])))


def _inside(v: float, lo: float, hi: float) -> bool:
    return lo - EPS <= v <= hi + EPS


# -- (1) sampled scenes lie inside the paper's ranges -----------------------------------------
def test_pen_samples_in_range():
    task = get_task("grasp_single_pen")
    for seed in SEEDS:
        sm = task.sample(seed)
        pos, quat = sm.poses["pen"]
        r = _mat(quat)
        assert _inside(pos[0], 0.18, 0.26) and _inside(pos[1], -0.20, -0.10), seed
        assert pos[2] == pytest.approx(TABLE_Z + PEN_R)  # lying on the table
        assert abs(r[2, 0]) < 1e-9  # long axis horizontal
        assert _inside(_heading(r[:, 0]), -30.0, 30.0), seed  # yaw from world +x
        assert sm.variant == 0


def test_lying_bottle_samples_in_range():
    task = get_task("grasp_single_bottle")
    for seed in SEEDS:
        sm = task.sample(seed)
        pos, quat = sm.poses["bottle"]
        r = _mat(quat)
        assert _inside(pos[0], 0.20, 0.28) and _inside(pos[1], -0.16, -0.04), seed
        assert pos[2] == pytest.approx(TABLE_Z + BOTTLE_FACE_R)  # on a flat face
        assert abs(r[2, 2]) < 1e-9  # axis horizontal: lying
        assert _inside(_heading(r[:, 2]), -22.5, 22.5), seed
        assert sm.variant == 0


@pytest.mark.parametrize("name", ["grasp_single_bottle_upright", "place_single_bottle_upright"])
def test_upright_bottle_samples_in_range(name):
    task = get_task(name)
    for seed in SEEDS:
        sm = task.sample(seed)
        pos, quat = sm.poses["bottle"]
        assert _inside(pos[0], 0.20, 0.28) and _inside(pos[1], -0.16, -0.04), seed
        assert pos[2] == pytest.approx(TABLE_Z + BOTTLE_HALF_H)
        assert np.allclose(_mat(quat), np.eye(3))  # fixed upright orientation
        assert sm.variant == 0
        if name == "place_single_bottle_upright":
            pad, pad_quat = sm.poses["pad"]
            assert _inside(pad[0], 0.03, 0.09) and _inside(pad[1], 0.07, 0.13), seed
            assert pad[2] == pytest.approx(TABLE_Z + 0.003)
            assert np.allclose(_mat(pad_quat), np.eye(3))


def test_leaning_pen_samples_in_range():
    task = get_task("grasp_pen_leaning_cube")
    for seed in SEEDS:
        sm = task.sample(seed)
        pos, quat = sm.poses["pen"]
        r = _mat(quat)
        axis = r[:, 0] if r[2, 0] > 0 else -r[:, 0]  # pointing up the pen
        lower = pos - PEN_HALF_SEG * axis
        assert _inside(lower[0], 0.16, 0.22) and _inside(lower[1], -0.24, -0.20), seed
        assert lower[2] == pytest.approx(TABLE_Z + PEN_R)  # lower end on the table
        assert np.degrees(np.arcsin(axis[2])) == pytest.approx(30.0)  # fixed 30 deg lean
        assert _inside(_heading(axis) - 90.0, -15.0, 15.0), seed  # yaw 0 = rising along +y
        block, block_quat = sm.poses["block"]
        assert block[2] == pytest.approx(TABLE_Z + 0.04)  # the 0.08 m cube on the table
        # the pen's upper end reaches the block's near face (within 1 mm)
        upper = pos + PEN_HALF_SEG * axis
        normal = _mat(block_quat)[:, 1]
        face_dist = np.dot(block - upper, normal) - 0.04
        assert face_dist == pytest.approx(PEN_R, abs=1e-3)
        assert sm.variant == 0


def test_samples_are_deterministic():
    for name in (*GRASPS, "place_single_bottle_upright"):
        task = get_task(name)
        a, b = task.sample(1234), task.sample(1234)
        for k in a.poses:
            assert np.array_equal(a.poses[k][0], b.poses[k][0])
            assert np.array_equal(a.poses[k][1], b.poses[k][1])


# -- (2) predicates on constructed states ----------------------------------------------------
@pytest.mark.parametrize("name", list(GRASPS))
def test_grasp_predicate_thresholds(name):
    obj = GRASPS[name][0]
    task = get_task(name)

    def ev(dz: float, closed: bool):
        sb = StateBuilder(task).move(obj, [0.0, 0.0, dz]).grip("right", not closed)
        return sb.evaluate()

    assert bool(ev(0.0501, True).success)
    assert not bool(ev(0.0499, True).success)  # "lifted > 50 mm"
    assert not bool(ev(0.10, False).success)  # right gripper must be closed
    e = ev(0.0501, True)
    assert bool(e.checks["lifted"]) and bool(e.checks["gripper_closed"])
    assert e.subgoals.shape == (len(task.checkpoints) - 1,)
    assert task.checkpoints[-1] == "completed"


@pytest.mark.parametrize("name", list(GRASPS))
def test_grasp_checkpoint_flags(name):
    obj = GRASPS[name][0]
    task = get_task(name)
    sb = StateBuilder(task)
    sb.gc[0] = sb.pos(obj) + [0.0, 0.0, 0.029]
    assert bool(sb.evaluate().subgoals[0])  # reached: GC within 30 mm
    sb.gc[0] = sb.pos(obj) + [0.0, 0.0, 0.031]
    assert not bool(sb.evaluate().subgoals[0])
    sb.grip("right", False)
    assert not bool(sb.evaluate().subgoals[1])  # closed but not touching
    sb.touch(obj, "right_gripper")
    assert bool(sb.evaluate().subgoals[1])  # grasped


PAD_TOP_REST = 0.003 + 0.06  # bottle origin above the pad centre when standing on it


def _placed(sb: StateBuilder, dx=0.0, dy=0.0, dz=0.0) -> StateBuilder:
    sb.set_pos("bottle", sb.pos("pad") + [dx, dy, PAD_TOP_REST + dz])
    return sb.touch("bottle", "pad").grip("right", True).latch("was_lifted")


def test_place_bottle_success_and_tolerances():
    task = get_task("place_single_bottle_upright")
    assert task.step_budget == 100
    assert bool(_placed(StateBuilder(task)).evaluate().success)
    for dx, dy in ((0.0399, 0.0), (-0.0399, 0.0), (0.0, 0.0399), (0.0, -0.0399)):
        assert bool(_placed(StateBuilder(task), dx=dx, dy=dy).evaluate().success)
    for dx, dy in ((0.0401, 0.0), (-0.0401, 0.0), (0.0, 0.0401), (0.0, -0.0401)):
        e = _placed(StateBuilder(task), dx=dx, dy=dy).evaluate()
        assert not bool(e.success) and not bool(e.checks["xy_within_tolerance"])
    for dz in (0.0349, -0.0349):
        assert bool(_placed(StateBuilder(task), dz=dz).evaluate().success)
    for dz in (0.0351, -0.0351):
        e = _placed(StateBuilder(task), dz=dz).evaluate()
        assert not bool(e.success) and not bool(e.checks["height_within_tolerance"])


def test_place_bottle_pad_displacement_contact_gripper():
    task = get_task("place_single_bottle_upright")
    sb = _placed(StateBuilder(task))
    sb.move("pad", [0.0019, 0.0, 0.0]).set_pos("bottle", sb.pos("pad") + [0, 0, PAD_TOP_REST])
    assert bool(sb.evaluate().success)
    sb = _placed(StateBuilder(task))
    sb.move("pad", [0.0021, 0.0, 0.0]).set_pos("bottle", sb.pos("pad") + [0, 0, PAD_TOP_REST])
    e = sb.evaluate()
    assert not bool(e.success) and not bool(e.checks["target_not_displaced"])
    e = _placed(StateBuilder(task)).touch("bottle", "pad", False).evaluate()
    assert not bool(e.success) and not bool(e.checks["contact"])
    e = _placed(StateBuilder(task)).grip("right", False).evaluate()
    assert not bool(e.success) and not bool(e.checks["gripper_open"])


def test_place_bottle_lift_latch():
    task = get_task("place_single_bottle_upright")
    # placed but never lifted: no success, and the latch stays unset
    e = _placed(StateBuilder(task)).latch("was_lifted", False).evaluate()
    assert not bool(e.success) and not bool(e.latched[0])
    # a latch set earlier keeps counting
    e = _placed(StateBuilder(task)).evaluate()
    assert bool(e.success) and bool(e.latched[0])
    # lifting sets the latch: >= 50 mm above the settled height
    sb = StateBuilder(task).move("bottle", [0.0, 0.0, 0.0501])
    assert bool(sb.evaluate().latched[0])
    sb = StateBuilder(task).move("bottle", [0.0, 0.0, 0.0499])
    assert not bool(sb.evaluate().latched[0])


# -- (3) experts through the batch (C MuJoCo) ------------------------------------------------
# slow: test_tasks.py::test_expert_solves_first_two_verified_seeds[name] runs this expert on
# the same seeds (1000, 1001) in the default run, with these assertions and more (a seed
# whose reset gate fails is not run: no success).
@pytest.mark.slow
@pytest.mark.parametrize("name", [*GRASPS, "place_single_bottle_upright"])
def test_expert_succeeds(name):
    task = get_task(name)
    for ep in expert_episodes(name, [1000, 1001]):  # run once, shared with test_tasks.py
        assert ep.settle.ok, ep.settle.reason
        assert ep.success, (ep.seed, ep.end)
        assert ep.steps <= task.step_budget
        progress = [a["progress"] for a in ep.actions]
        assert progress == sorted(progress)  # monotone
        assert progress[-1] == len(task.checkpoints)


def test_expert_actions_stay_on_the_interface():
    tb = TaskBatch(get_task("grasp_pen_leaning_cube"), 1, backend="c")
    (ep,) = run_experts(tb, [1002])
    for rec in ep.actions:
        a = rec["action"]
        assert a["action"] in {
            "gripper.move_world",
            "gripper.rotate_local",
            "gripper.open",
            "gripper.close",
        }
        if "distance_mm" in a:
            assert rc.MOVE_MM_RANGE[0] <= a["distance_mm"] <= rc.MOVE_MM_RANGE[1]
        if "angle_deg" in a:
            assert rc.ROTATE_DEG_RANGE[0] <= a["angle_deg"] <= rc.ROTATE_DEG_RANGE[1]
