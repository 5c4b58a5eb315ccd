"""The held-out bottle variants of the transfer track: grasp_single_bottle_heldout,
grasp_single_bottle_upright_heldout, place_single_bottle_upright_heldout.

Ranges and thresholds are the base families' (paper tables tab:seed-spec-grasp and
tab:seed-spec-place), transcribed here independently of the modules' constants; the held-out
containers' dimensions are those stated in their module docstrings and object files.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from tests.task_states import StateBuilder
from vabench.tasks import get_task
from vabench.tasks.task_batch import TaskBatch, run_experts

TABLE_Z = 0.741
SEEDS = range(1000, 1200)
EPS = 1e-9
X_RANGE, Y_RANGE, YAW_DEG = (0.20, 0.28), (-0.16, -0.04), (-22.5, 22.5)
PAD_X, PAD_Y, PAD_HALF_THICK = (0.03, 0.09), (0.07, 0.13), 0.003
SHAMPOO_HALF_T = 0.019  # lying on a broad face: centre 19 mm above the table
SQUARE_HALF_H = 0.090  # standing: body centre 90 mm above the table
VARIANTS = {  # variant: base
    "grasp_single_bottle_heldout": "grasp_single_bottle",
    "grasp_single_bottle_upright_heldout": "grasp_single_bottle_upright",
    "place_single_bottle_upright_heldout": "place_single_bottle_upright",
}
GRASPS = ["grasp_single_bottle_heldout", "grasp_single_bottle_upright_heldout"]
PLACE = "place_single_bottle_upright_heldout"


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


def _inside(v: float, lo: float, hi: float) -> bool:
    return lo - EPS <= v <= hi + EPS


# -- the transfer-track identity -------------------------------------------------------------
@pytest.mark.parametrize("name", list(VARIANTS))
def test_variant_keeps_the_base_interface(name):
    task, base = get_task(name), get_task(VARIANTS[name])
    assert task.suite == "transfer" and task.base_family == base.name
    assert task.instruction == base.instruction
    assert (task.arms, task.step_budget) == (base.arms, base.step_budget)
    assert task.checkpoints == base.checkpoints and task.latches == base.latches
    assert task.contact_pairs == base.contact_pairs


# -- (1) sampled scenes lie inside the base's ranges -----------------------------------------
def test_lying_shampoo_samples_in_range():
    task = get_task("grasp_single_bottle_heldout")
    for seed in SEEDS:
        sm = task.sample(seed)
        pos, quat = sm.poses["bottle"]
        r = _mat(quat)
        assert _inside(pos[0], *X_RANGE) and _inside(pos[1], *Y_RANGE), seed
        assert pos[2] == pytest.approx(TABLE_Z + SHAMPOO_HALF_T)  # on a broad face
        assert abs(r[2, 2]) < 1e-9  # axis (local z) horizontal: lying
        assert r[2, 1] == pytest.approx(1.0)  # thickness (local y) vertical
        heading = np.degrees(np.arctan2(r[1, 2], r[0, 2]))  # yaw from world +x, pump end
        assert _inside(heading, *YAW_DEG), seed
        assert sm.variant == 0


@pytest.mark.parametrize("name", ["grasp_single_bottle_upright_heldout", PLACE])
def test_upright_square_samples_in_range(name):
    task = get_task(name)
    for seed in SEEDS:
        sm = task.sample(seed)
        pos, quat = sm.poses["bottle"]
        assert _inside(pos[0], *X_RANGE) and _inside(pos[1], *Y_RANGE), seed
        assert pos[2] == pytest.approx(TABLE_Z + SQUARE_HALF_H)
        assert np.allclose(_mat(quat), np.eye(3))  # fixed upright, faces along x and y
        assert sm.variant == 0
        if name == PLACE:
            pad, pad_quat = sm.poses["pad"]
            assert _inside(pad[0], *PAD_X) and _inside(pad[1], *PAD_Y), seed
            assert pad[2] == pytest.approx(TABLE_Z + PAD_HALF_THICK)
            assert np.allclose(_mat(pad_quat), np.eye(3))


@pytest.mark.parametrize("name", list(VARIANTS))
def test_variant_seeds_give_other_scenes_than_base_seeds(name):
    task, base = get_task(name), get_task(VARIANTS[name])
    for seed in SEEDS:
        a, b = task.sample(seed).poses, base.sample(seed).poses
        for obj in a:  # every object is placed elsewhere than in the base's scene of the seed
            assert np.linalg.norm(a[obj][0][:2] - b[obj][0][:2]) > 1e-6, (seed, obj)
    a, b = task.sample(1234), task.sample(1234)
    for obj in a.poses:
        assert np.array_equal(a.poses[obj][0], b.poses[obj][0])
        assert np.array_equal(a.poses[obj][1], b.poses[obj][1])


# -- (2) predicates on constructed states ----------------------------------------------------
@pytest.mark.parametrize("name", GRASPS)
def test_grasp_predicate_thresholds(name):
    task = get_task(name)

    def ev(dz: float, closed: bool):
        return StateBuilder(task).move("bottle", [0.0, 0.0, dz]).grip("right", not closed)

    assert bool(ev(0.0501, True).evaluate().success)
    assert not bool(ev(0.0499, True).evaluate().success)  # "lifted > 50 mm"
    e = ev(0.10, False).evaluate()
    assert not bool(e.success) and not bool(e.checks["gripper_closed"])  # must be closed
    e = ev(0.0501, True).evaluate()
    assert bool(e.checks["lifted"]) and bool(e.checks["gripper_closed"])
    assert task.latches == ()  # nothing latched: a bottle dropped again is no success
    assert not bool(ev(0.0499, True).evaluate().checks["lifted"])


@pytest.mark.parametrize("name", GRASPS)
def test_grasp_checkpoint_flags(name):
    task = get_task(name)
    sb = StateBuilder(task)
    sb.gc[0] = sb.pos("bottle") + [0.0, 0.029, 0.0]
    assert bool(sb.evaluate().subgoals[0])  # reached: GC within 30 mm of the body's centre
    sb.gc[0] = sb.pos("bottle") + [0.0, 0.031, 0.0]
    assert not bool(sb.evaluate().subgoals[0])
    sb.grip("right", False)
    assert not bool(sb.evaluate().subgoals[1])  # closed but not touching
    sb.touch("bottle", "right_gripper")
    assert bool(sb.evaluate().subgoals[1])  # grasped
    sb.move("bottle", [0.0, 0.0, 0.0501])
    assert bool(sb.evaluate().subgoals[2])  # lifted


REST = PAD_HALF_THICK + SQUARE_HALF_H  # the container's origin above the pad centre, upright


def _placed(dx=0.0, dy=0.0, dz=0.0) -> StateBuilder:
    sb = StateBuilder(get_task(PLACE))
    sb.set_pos("bottle", sb.pos("pad") + [dx, dy, REST + dz])
    return sb.touch("bottle", "pad").grip("right", True).latch("was_lifted")


def test_place_success_and_tolerances():
    assert bool(_placed().evaluate().success)
    for dx, dy in ((0.0399, 0.0), (-0.0399, 0.0), (0.0, 0.0399), (0.0, -0.0399)):
        assert bool(_placed(dx=dx, dy=dy).evaluate().success)
    for dx, dy in ((0.0401, 0.0), (-0.0401, 0.0), (0.0, 0.0401), (0.0, -0.0401)):
        e = _placed(dx=dx, dy=dy).evaluate()
        assert not bool(e.success) and not bool(e.checks["xy_within_tolerance"])
    for dz in (0.0349, -0.0349):
        assert bool(_placed(dz=dz).evaluate().success)
    for dz in (0.0351, -0.0351):
        e = _placed(dz=dz).evaluate()
        assert not bool(e.success) and not bool(e.checks["height_within_tolerance"])


def test_place_square_bottle_lying_on_the_pad_fails_the_height_check():
    # lying on a face its centre is 25 mm above the pad's top: 65 mm below upright resting
    sb = _placed(dz=(PAD_HALF_THICK + 0.025) - REST)
    sb.set_quat("bottle", [np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0])
    e = sb.evaluate()
    assert not bool(e.success) and not bool(e.checks["height_within_tolerance"])


def test_place_pad_displacement_contact_gripper():
    sb = _placed()
    sb.move("pad", [0.0019, 0.0, 0.0]).set_pos("bottle", sb.pos("pad") + [0, 0, REST])
    assert bool(sb.evaluate().success)
    sb = _placed()
    sb.move("pad", [0.0, 0.0021, 0.0]).set_pos("bottle", sb.pos("pad") + [0, 0, REST])
    e = sb.evaluate()
    assert not bool(e.success) and not bool(e.checks["target_not_displaced"])
    e = _placed().touch("bottle", "pad", False).evaluate()
    assert not bool(e.success) and not bool(e.checks["contact"])
    e = _placed().grip("right", False).evaluate()
    assert not bool(e.success) and not bool(e.checks["gripper_open"])


def test_place_lift_latch_and_checkpoints():
    e = _placed().latch("was_lifted", False).evaluate()
    assert not bool(e.success) and not bool(e.latched[0])  # placed but never lifted
    e = _placed().evaluate()
    assert bool(e.success) and bool(e.latched[0])  # a latch set earlier keeps counting
    task = get_task(PLACE)
    assert bool(StateBuilder(task).move("bottle", [0, 0, 0.0501]).evaluate().latched[0])
    assert not bool(StateBuilder(task).move("bottle", [0, 0, 0.0499]).evaluate().latched[0])
    # transported (placement checks) and released (open over the pad) before completion
    e = _placed().grip("right", False).touch("bottle", "pad", False).evaluate()
    assert bool(e.subgoals[3]) and not bool(e.subgoals[4]) and not bool(e.success)


# -- (3) the held-out containers differ from the base's water bottle -------------------------
def _bottle_geoms(name: str) -> tuple[mujoco.MjModel, list[int]]:
    model = get_task(name).build_model(0)
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "bottle")
    return model, [g for g in range(model.ngeom) if model.geom_bodyid[g] == body]


def _points(model: mujoco.MjModel, g: int) -> np.ndarray:
    """A geom's shape in its body's frame: mesh vertices, or the corners of its local AABB
    (exact for boxes, a bound for the round visual parts)."""
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
        m = model.geom_dataid[g]
        local = model.mesh_vert[
            model.mesh_vertadr[m] : model.mesh_vertadr[m] + model.mesh_vertnum[m]
        ]
    else:
        c, h = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        local = c + signs * h
    return local @ _mat(model.geom_quat[g]).T + model.geom_pos[g]


def _extents(name: str, colliding_body_only: bool) -> np.ndarray:
    """The container's points: its colliding body geom (the largest colliding geom), or every
    geom, visual ones included (the overall size)."""
    model, geoms = _bottle_geoms(name)
    if colliding_body_only:
        colliding = [g for g in geoms if model.geom_contype[g]]
        geoms = [max(colliding, key=lambda g: np.prod(model.geom_aabb[g, 3:]))]
    return np.concatenate([_points(model, g) for g in geoms])


def _section(points: np.ndarray) -> tuple[float, float, float]:
    """Width (local x), thickness (local y) and the diagonal-to-face ratio of the section: the
    support along (1, 1)/sqrt 2 over the mean support along x and y (1 for a round section,
    sqrt 2 for a square one)."""
    width = np.ptp(points[:, 0])
    thick = np.ptp(points[:, 1])
    diag = np.max(points[:, :2] @ np.array([1.0, 1.0]) / np.sqrt(2.0))
    return width, thick, diag / ((width + thick) / 4.0)


def test_water_bottle_reference_dimensions():
    # the base's bottle as its docstring states it: round, 64 mm across, 168 mm tall
    for base in ("grasp_single_bottle", "grasp_single_bottle_upright"):
        w, t, squareness = _section(_extents(base, True))
        assert w == pytest.approx(0.064, abs=0.0015) and t == pytest.approx(0.064, abs=0.0015)
        assert squareness < 1.05
        assert np.ptp(_extents(base, False)[:, 2]) == pytest.approx(0.168, abs=0.003)


def test_shampoo_differs_from_water_bottle_in_shape_and_size():
    w, t, _ = _section(_extents("grasp_single_bottle_heldout", True))
    bw, bt, _ = _section(_extents("grasp_single_bottle", True))
    assert w == pytest.approx(0.056, abs=1e-4) and t == pytest.approx(0.038, abs=1e-4)
    assert w / t > 1.4 and bw / bt < 1.02  # flat section versus round
    assert bw - w > 0.005 and bt - t > 0.02  # narrower and thinner
    length = np.ptp(_extents("grasp_single_bottle_heldout", False)[:, 2])
    base_length = np.ptp(_extents("grasp_single_bottle", False)[:, 2])
    assert length == pytest.approx(0.205, abs=0.002) and length - base_length > 0.03
    # lying, the body's centre sits lower: 19 mm versus the water bottle's 31.4 mm
    assert get_task("grasp_single_bottle_heldout").sample(1000).poses["bottle"][0][2] < (
        get_task("grasp_single_bottle").sample(1000).poses["bottle"][0][2] - 0.01
    )


@pytest.mark.parametrize("name", ["grasp_single_bottle_upright_heldout", PLACE])
def test_square_bottle_differs_from_water_bottle_in_shape_and_size(name):
    w, t, squareness = _section(_extents(name, True))
    bw, _, base_squareness = _section(_extents(VARIANTS[name], True))
    assert w == pytest.approx(0.050, abs=1e-4) and t == pytest.approx(0.050, abs=1e-4)
    assert squareness > 1.35 and base_squareness < 1.05  # square section versus round
    assert bw - w > 0.01  # slimmer
    height = np.ptp(_extents(name, False)[:, 2])
    base_height = np.ptp(_extents(VARIANTS[name], False)[:, 2])
    assert height == pytest.approx(0.220, abs=0.002) and height - base_height > 0.04


def _visible_colours(name: str) -> np.ndarray:
    model, geoms = _bottle_geoms(name)
    out = []
    for g in geoms:
        if model.geom_group[g] <= 2:  # group 3: hidden collision shapes
            mat = model.geom_matid[g]
            out.append(model.mat_rgba[mat][:3] if mat >= 0 else model.geom_rgba[g][:3])
    return np.array(out)


@pytest.mark.parametrize("name", list(VARIANTS))
def test_held_out_container_has_other_colours(name):
    ours, base = _visible_colours(name), _visible_colours(VARIANTS[name])
    # every main colour (not near-white or near-black trim) of the held-out container is more
    # than 0.3 (RGB distance) from every main colour of the water bottle
    base_main = [c for c in base if 0.2 < np.mean(c) < 0.9]
    ours_main = [c for c in ours if 0.2 < np.mean(c) < 0.9]
    assert ours_main and base_main
    for c in ours_main:
        assert min(np.linalg.norm(c - b) for b in base_main) > 0.3, c


# -- (4) experts through the batch (C MuJoCo) ------------------------------------------------
@pytest.mark.parametrize("name", list(VARIANTS))
def test_expert_succeeds(name):
    task = get_task(name)
    tb = TaskBatch(task, 2, backend="c")
    episodes = run_experts(tb, [1000, 1001])
    views = tb.views([0, 1])
    for slot, ep in enumerate(episodes):
        assert ep.settle.ok, ep.settle.reason
        assert ep.success, (ep.seed, ep.end)
        assert ep.steps <= task.step_budget // 2  # with margin
        progress = [a["progress"] for a in ep.actions]
        assert progress == sorted(progress) and progress[-1] == len(task.checkpoints)
        v = views[slot]
        if name in GRASPS:  # really held: not flung up out of the fingers
            assert np.linalg.norm(v.pos("bottle") - v.arms["right"].gc) < 0.03
        else:  # standing on the pad
            assert v.mat("bottle")[2, 2] > np.cos(np.radians(5))
