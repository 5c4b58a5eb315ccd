"""put_everything_in_basket: ranges of 200 consecutive seeds (spacing, nothing starts in the
basket), the predicate on constructed states at each threshold (inside / outside the interior in
x and y, held / released, stacked inside, above the rim, 4 of 5), the scene's geometry, and the
expert through the batch.

Numbers are transcribed from the family's docstring and the object files, independently of the
module's constants.
"""

from __future__ import annotations

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from tests.expert_runs import expert_episodes
from tests.task_states import StateBuilder
from vabench.tasks import BASKET_DEMONSTRATIONS, get_task
from vabench.tasks.base import advance_progress
from vabench.tasks.manifests import load_manifest

NAME = "put_everything_in_basket"
TABLE_Z = 0.741
SEEDS = range(1000, 1200)
EPS = 1e-9
OBJECTS = ("cube", "small_cube", "bottle", "upright_bottle", "pen")

BASKET_X, BASKET_Y = (0.10, 0.14), (0.03, 0.05)
OBJ_X, OBJ_Y = (0.02, 0.40), (-0.28, -0.10)
YAW_DEG = {"cube": 45.0, "small_cube": 45.0, "bottle": 22.5, "pen": 30.0}
MIN_GAP, FINGER_GAP = 0.04, 0.005
INNER = (0.13, 0.10)  # interior half-sizes: 260 x 200 mm
OUTER = (0.142, 0.112)  # 12 mm walls
FLOOR_TOP, RIM = 0.024, 0.079  # above the table
TOL = 0.002  # contact tolerance of the interior test

FACE_R = 0.032 * np.cos(np.pi / 16)  # the bottles' 16-gon: centre to a flat face
REST = {  # centre above its support, resting as sampled
    "cube": 0.025,
    "small_cube": 0.02,
    "bottle": FACE_R,
    "upright_bottle": 0.06,
    "pen": 0.007,
}


def _mat(quat) -> np.ndarray:
    w, x, y, z = np.asarray(quat, float) / np.linalg.norm(quat)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rect(centre, u, along: tuple[float, float], across: float) -> np.ndarray:
    """Corners of a rectangle spanning along[0]..along[1] on the unit axis u, +-across on its
    normal."""
    u = np.asarray(u, float)[:2] / np.linalg.norm(np.asarray(u, float)[:2])
    v = np.array([-u[1], u[0]])
    c = np.asarray(centre, float)[:2]
    return np.array(
        [c + a * u + s * across * v for a, s in ((along[0], -1), (along[1], -1))]
        + [c + a * u + s * across * v for a, s in ((along[1], 1), (along[0], 1))]
    )


def _footprint(name: str, pos, quat) -> np.ndarray:
    r = _mat(quat)
    if name in ("cube", "small_cube"):
        h = REST[name]
        return _rect(pos, r[:, 0], (-h, h), h)
    if name == "bottle":  # axis = local z: bottom face at -60 mm, neck end at +105 mm
        return _rect(pos, r[:, 2], (-0.06, 0.105), FACE_R)
    if name == "pen":
        return _rect(pos, r[:, 0], (-0.07, 0.07), 0.007)
    return _rect(pos, [1.0, 0.0], (-0.032, 0.032), 0.032)  # upright bottle


def _segment_distance(p, a, b) -> float:
    ab = b - a
    t = np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + t * ab)))


def _cross(a, b) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _contains(poly, p) -> bool:
    cross = [_cross(poly[(i + 1) % 4] - poly[i], p - poly[i]) for i in range(4)]
    return all(c >= 0 for c in cross) or all(c <= 0 for c in cross)


def _crosses(a1, a2, b1, b2) -> bool:
    def side(p, q, r):
        return np.sign(_cross(q - p, r - p))

    return side(a1, a2, b1) != side(a1, a2, b2) and side(b1, b2, a1) != side(b1, b2, a2)


def _distance(p, q) -> float:
    """Distance between two convex quadrilaterals (0 if they overlap)."""
    if any(_contains(q, x) for x in p) or any(_contains(p, x) for x in q):
        return 0.0
    edges_p = [(p[i], p[(i + 1) % 4]) for i in range(4)]
    edges_q = [(q[i], q[(i + 1) % 4]) for i in range(4)]
    if any(_crosses(*e, *f) for e in edges_p for f in edges_q):
        return 0.0
    return min(
        min(_segment_distance(x, *f) for x in p for f in edges_q),
        min(_segment_distance(x, *e) for x in q for e in edges_p),
    )


def _yaw_deg(quat) -> float:
    w, x, y, z = quat
    assert abs(x) < 1e-12 and abs(y) < 1e-12  # resting flat: a pure yaw
    return float(np.degrees(2 * np.arctan2(z, w)))


def _inside(v, lo, hi) -> bool:
    return lo - EPS <= v <= hi + EPS


# -- ranges ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def samples():
    task = get_task(NAME)
    return {seed: task.sample(seed) for seed in SEEDS}


def test_two_hundred_seeds_stay_in_range_spaced_and_out_of_the_basket(samples):
    for seed in SEEDS:
        poses = samples[seed].poses
        assert set(poses) == {*OBJECTS, "basket"}, seed
        bpos, bquat = poses["basket"]
        assert _inside(bpos[0], *BASKET_X) and _inside(bpos[1], *BASKET_Y), seed
        assert bpos[2] == pytest.approx(TABLE_Z) and _yaw_deg(bquat) == 0.0
        outline = _rect(bpos, [1.0, 0.0], (-OUTER[0], OUTER[0]), OUTER[1])
        rects = {}
        for name in OBJECTS:
            pos, quat = poses[name]
            assert _inside(pos[0], *OBJ_X) and _inside(pos[1], *OBJ_Y), (seed, name)
            assert pos[2] == pytest.approx(TABLE_Z + REST[name]), (seed, name)
            r = _mat(quat)
            if name == "bottle":  # lying: axis horizontal, heading within +-22.5 deg
                assert abs(r[2, 2]) < 1e-9
                heading = np.degrees(np.arctan2(r[1, 2], r[0, 2]))
                assert abs(heading) <= YAW_DEG[name] + EPS, seed
            elif name == "upright_bottle":
                np.testing.assert_allclose(quat, [1.0, 0.0, 0.0, 0.0])
            else:
                assert abs(_yaw_deg(quat)) <= YAW_DEG[name] + EPS, (seed, name)
            rects[name] = _footprint(name, pos, quat)
            # nothing starts in (or near) the basket
            assert _distance(rects[name], outline) >= MIN_GAP - 1e-6, (seed, name)
        for i, a in enumerate(OBJECTS):
            for b in OBJECTS[i + 1 :]:
                assert _distance(rects[a], rects[b]) >= MIN_GAP - 1e-6, (seed, a, b)
        # the open fingers of a grasp across the pen's centre have room
        pos, quat = poses["pen"]
        fingers = _rect(pos, _mat(quat)[:, 0], (-0.012, 0.012), 0.057)
        for other in [outline] + [rects[n] for n in OBJECTS if n != "pen"]:
            assert _distance(fingers, other) >= FINGER_GAP - 1e-6, seed


def test_sampling_uses_the_whole_ranges(samples):
    xs = np.array([samples[s].poses["cube"][0][:2] for s in SEEDS])
    assert xs[:, 0].min() < 0.10 and xs[:, 0].max() > 0.32
    assert xs[:, 1].min() < -0.24 and xs[:, 1].max() > -0.14


# -- predicate -------------------------------------------------------------------------------
def _basket_state(placed=OBJECTS) -> StateBuilder:
    """Objects of `placed` resting on the basket floor, spread out, released, touching the
    basket; the rest where the seed put them."""
    b = StateBuilder(get_task(NAME))
    base = b.pos("basket").copy()
    spots = {
        "upright_bottle": (-0.085, 0.055),
        "cube": (-0.085, -0.055),
        "small_cube": (-0.02, -0.04),
        "pen": (0.02, 0.01),
        "bottle": (0.08, -0.02),
    }
    for name in placed:
        x, y = spots[name]
        b.set_pos(name, base + [x, y, FLOOR_TOP + REST[name]])
        if name in ("pen", "bottle"):  # lying along the basket's y
            _lay_along_y(b, name)
        b.touch(name, "basket")
    return b


def _lay_along_y(b: StateBuilder, name: str) -> None:
    if name == "pen":  # long axis = local x -> world y
        b.set_quat(name, [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    else:  # bottle on a flat face, axis (local z) -> world +y
        roll = np.array([np.cos(-np.pi / 32), 0.0, 0.0, np.sin(-np.pi / 32)])
        down = np.array([np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0])
        yaw = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
        b.set_quat(name, _qmul(yaw, _qmul(down, roll)))


def _qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def _placed(ev) -> dict[str, bool]:
    return {n: bool(ev.checks[f"{n}_placed"]) for n in OBJECTS}


def test_all_five_resting_in_the_basket_is_success():
    ev = _basket_state().evaluate()
    assert all(_placed(ev).values()) and bool(ev.success)
    assert np.asarray(ev.subgoals).tolist() == [True] * 4


def test_four_of_five_is_progress_four_without_success():
    ev = _basket_state(placed=OBJECTS[:4]).evaluate()
    assert sum(_placed(ev).values()) == 4 and not bool(ev.success)
    assert np.asarray(ev.subgoals).tolist() == [True, True, True, True]
    progress = advance_progress(jnp.array(0), jnp.asarray(ev.subgoals), jnp.asarray(ev.success))
    assert int(progress) == 4
    two = _basket_state(placed=OBJECTS[:2]).evaluate()
    assert np.asarray(two.subgoals).tolist() == [True, True, False, False]
    # progress never goes back: an object taken out again leaves the checkpoint reached
    again = advance_progress(progress, jnp.asarray(two.subgoals), jnp.asarray(two.success))
    assert int(again) == 4
    none = StateBuilder(get_task(NAME)).evaluate()
    assert not any(np.asarray(none.subgoals)) and not bool(none.success)


@pytest.mark.parametrize("axis", [0, 1])
@pytest.mark.parametrize(("beyond", "ok"), [(-0.0005, True), (0.0005, False)])
def test_cube_just_inside_or_outside_the_interior(axis, beyond, ok):
    """An axis-aligned 5 cm cube whose face lies `beyond` past the interior's wall face plus
    the 2 mm contact tolerance, on either side."""
    for sign in (1.0, -1.0):
        b = _basket_state()
        b.set_quat("cube", [1.0, 0.0, 0.0, 0.0])
        offset = np.zeros(3)
        offset[axis] = sign * (INNER[axis] + TOL - 0.025 + beyond)
        b.set_pos("cube", b.pos("basket") + offset + [0.0, 0.0, FLOOR_TOP + 0.025])
        ev = b.evaluate()
        assert bool(ev.checks["cube_inside"]) is ok and bool(ev.checks["cube_placed"]) is ok
        assert bool(ev.success) is ok


@pytest.mark.parametrize(("beyond", "ok"), [(-0.0005, True), (0.0005, False)])
def test_lying_bottle_neck_counts_in_the_footprint(beyond, ok):
    """The bottle along the basket's y: its neck end (105 mm from its centre) decides."""
    b = _basket_state()
    y = INNER[1] + TOL - 0.105 + beyond
    b.set_pos("bottle", b.pos("basket") + [0.08, y, FLOOR_TOP + FACE_R])
    assert bool(b.evaluate().checks["bottle_inside"]) is ok


@pytest.mark.parametrize(
    ("closed", "touching", "ok"),
    [(True, True, False), (False, True, True), (True, False, True), (False, False, True)],
)
def test_held_by_the_closed_gripper_is_not_placed(closed, touching, ok):
    b = _basket_state()
    b.grip("right", not closed).touch("small_cube", "right_gripper", touching)
    ev = b.evaluate()
    assert bool(ev.checks["small_cube_inside"])
    assert bool(ev.checks["small_cube_placed"]) is ok and bool(ev.success) is ok


def test_resting_on_an_object_inside_counts_and_on_one_outside_does_not():
    b = _basket_state()
    cube = b.pos("cube").copy()
    b.set_pos("small_cube", cube + [0.0, 0.0, 0.025 + 0.02])  # stacked on the red cube
    b.touch("small_cube", "basket", False).touch("cube", "small_cube")
    ev = b.evaluate()
    assert bool(ev.checks["small_cube_placed"]) and bool(ev.success)
    # the support is held by the closed gripper: the stack is not resting in the basket
    b.touch("cube", "right_gripper").grip("right", False)
    assert not bool(b.evaluate().checks["small_cube_placed"])
    # the support lies outside the basket (the stack sits on the table beside it)
    b2 = _basket_state()
    out = b2.pos("basket") + [0.0, -0.25, 0.025]
    b2.set_pos("cube", out).touch("cube", "basket", False)
    b2.set_pos("small_cube", out + [0.0, 0.0, 0.045]).touch("small_cube", "basket", False)
    b2.touch("cube", "small_cube")
    ev2 = b2.evaluate()
    assert not bool(ev2.checks["cube_inside"]) and not bool(ev2.checks["small_cube_placed"])


def test_above_the_rim_touching_nothing_is_not_placed():
    b = _basket_state()
    b.set_pos("small_cube", b.pos("basket") + [-0.02, -0.04, RIM + 0.03])
    b.touch("small_cube", "basket", False)
    ev = b.evaluate()
    assert bool(ev.checks["small_cube_inside"])  # over the interior...
    assert not bool(ev.checks["small_cube_placed"]) and not bool(ev.success)  # ...not in it


# -- scene geometry ----------------------------------------------------------------------------
def test_basket_geometry_and_mass():
    model = get_task(NAME).build_model(0)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "basket")
    assert model.body_subtreemass[bid] >= 3.0  # heavy: drops and brushes do not slide it

    def box(name):
        gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"basket_{name}")
        return model.geom_pos[gid], model.geom_size[gid]

    pos, size = box("wall_px")
    assert pos[0] - size[0] == pytest.approx(INNER[0]) and pos[0] + size[0] == pytest.approx(
        OUTER[0]
    )
    pos, size = box("wall_py")
    assert pos[1] - size[1] == pytest.approx(INNER[1]) and pos[1] + size[1] == pytest.approx(
        OUTER[1]
    )
    assert pos[2] + size[2] == pytest.approx(RIM)
    pos, size = box("floor")
    assert pos[2] + size[2] == pytest.approx(FLOOR_TOP)
    assert size[2] >= 0.01  # a thick floor: a dropped object cannot pass its middle plane


def test_objects_have_distinct_colours_and_the_pen_collides_as_a_box():
    model = get_task(NAME).build_model(0)
    colours = {}
    for name in OBJECTS:
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == bid]
        visible = [g for g in geoms if model.geom_group[g] <= 2]
        # the largest visible geom gives the object its colour
        main = max(visible, key=lambda g: np.prod(model.geom_size[g][model.geom_size[g] > 0]))
        mat = model.geom_matid[main]
        colours[name] = tuple(np.round(model.mat_rgba[mat][:3], 2))
        if name == "pen":
            colliding = [g for g in geoms if model.geom_contype[g] or model.geom_conaffinity[g]]
            assert [model.geom_type[g] for g in colliding] == [mujoco.mjtGeom.mjGEOM_BOX]
    assert len(set(colours.values())) == len(OBJECTS), colours


def test_task_fields():
    task = get_task(NAME)
    assert task.suite == "long_horizon" and task.arms == ("right",)
    assert task.step_budget == 250 and task.demonstrations == BASKET_DEMONSTRATIONS
    assert task.checkpoints == ("placed_1", "placed_2", "placed_3", "placed_4", "completed")


# -- expert ------------------------------------------------------------------------------------
def test_expert_places_all_five_on_two_verified_seeds():
    task = get_task(NAME)
    seeds = load_manifest(NAME)["retained"][:2]
    for ep in expert_episodes(NAME, seeds):  # run once, shared with test_tasks.py
        assert ep.success, (ep.seed, ep.end)
        assert ep.steps <= task.step_budget - 100  # margin: five placements in ~115 steps
        progress = [a["progress"] for a in ep.actions]
        assert progress == sorted(progress) and progress[-1] == 5
        assert all(a["valid"] for a in ep.actions)
