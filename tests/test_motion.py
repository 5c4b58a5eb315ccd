"""The Must-holds of the simulator core with real MuJoCo physics: on C MuJoCo, and on MJX (JAX
on the CPU; `slow`: its compile alone takes minutes here), through the batch interface both
share (`get_state` compares a slot's whole state)."""

from __future__ import annotations

import itertools

import jax.numpy as jnp
import numpy as np
import pytest

from tests.conftest import N_SLOTS
from vabench.sim_mjx import controller as ctl
from vabench.sim_mjx.cpu import CpuBatch

BACKENDS = ["c", pytest.param("mjx", marks=pytest.mark.slow)]


@pytest.fixture(scope="module", params=BACKENDS)
def backend(request):
    return request.param


@pytest.fixture(scope="module")
def batches(backend, request, probe_model):
    """(the 18-slot batch, the 1-slot batch) of `backend`."""
    if backend == "mjx":
        return request.getfixturevalue("mjx_batch"), request.getfixturevalue("mjx_single")
    return CpuBatch(probe_model, N_SLOTS), CpuBatch(probe_model, 1)


@pytest.fixture
def home_batch(batches, probe_task, probe_model):
    """The 18-slot batch with every slot reset to seed 0 of probe_cube at home."""
    q = probe_task.initial_qpos(probe_model, 0)
    batch = batches[0]
    batch.reset(range(N_SLOTS), np.broadcast_to(q, (N_SLOTS, probe_model.nq)), settle_steps=25)
    return batch


@pytest.fixture
def single(batches):
    return batches[1]


def _state(batch, slot=0):
    return batch.get_state([slot])


def _assert_same_state(a, b):
    assert a.keys() == b.keys()
    for field in a:
        np.testing.assert_array_equal(a[field], b[field], err_msg=field)


AXES = {"x": 0, "y": 1, "z": 2}
LOCAL = {"rx": 0, "ry": 1, "rz": 2}


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0)))


def _rotation_angle_deg(r0, r1):
    """Angle of the relative rotation r0^T r1."""
    rel = r0.T @ r1
    return np.degrees(np.arccos(np.clip((np.trace(rel) - 1.0) / 2.0, -1.0, 1.0)))


def test_world_translation(home_batch):
    """GC moves d along the axis within 2 mm, off-axis drift < 2 mm, orientation < 1 deg."""
    cases = list(itertools.product("xyz", "+-", (1, 37, 100)))
    assert len(cases) == N_SLOTS
    before = home_batch.proprio()
    results = home_batch.step(
        [
            {"action": "gripper.move_world", "axis": a, "sign": s, "distance_mm": d}
            for a, s, d in cases
        ]
    )
    after = home_batch.proprio()
    for slot, (axis, sign, dist) in enumerate(cases):
        res = results[slot]
        assert res.valid and res.planner_success and res.executed, (slot, res)
        assert not res.clipped["right"]
        move = (after.gc[slot, 0] - before.gc[slot, 0]) * 1000.0
        along = move[AXES[axis]] * (1 if sign == "+" else -1)
        off = np.delete(move, AXES[axis])
        assert abs(along - dist) < 2.0, (axis, sign, dist, move)
        assert np.all(np.abs(off) < 2.0), (axis, sign, dist, move)
        assert _rotation_angle_deg(before.rot[slot, 0], after.rot[slot, 0]) < 1.0


def test_local_rotation(home_batch):
    """Rotations about rx|ry|rz by up to 90 deg turn the gripper axes by the commanded angle
    within 1 deg; GC drifts under 3 mm. Start: a top-down grasp posture, except for +ry, which
    would point the fingers back at the robot: those start pointing forward and end top-down."""
    cases = list(itertools.product(("rx", "ry", "rz"), "+-", (10, 45, 90)))
    tilt = home_batch.step(
        [
            {"action": "gripper.rotate_local", "axis": "ry", "sign": "-", "angle_deg": 50}
            if (a, s) == ("ry", "+")
            else {"action": "gripper.rotate_local", "axis": "ry", "sign": "+", "angle_deg": 40}
            for a, s, _ in cases
        ]
    )
    assert all(r.planner_success for r in tilt)
    start = home_batch.proprio()
    np.testing.assert_allclose(start.rot[0, 0][:, 0], [0.0, 0.0, -1.0], atol=1e-3)  # top-down
    np.testing.assert_allclose(start.rot[6, 0][:, 0], [0.0, 1.0, 0.0], atol=1e-3)  # forward
    results = home_batch.step(
        [
            {"action": "gripper.rotate_local", "axis": a, "sign": s, "angle_deg": d}
            for a, s, d in cases
        ]
    )
    end = home_batch.proprio()
    for slot, (axis, sign, angle) in enumerate(cases):
        assert results[slot].planner_success, (axis, sign, angle)
        r0, r1 = start.rot[slot, 0], end.rot[slot, 0]
        assert abs(_rotation_angle_deg(r0, r1) - angle) < 1.0, (axis, sign, angle)
        # the rotation is about the commanded local axis, right-handed
        k = LOCAL[axis]
        np.testing.assert_allclose(r1[:, k], r0[:, k], atol=np.sin(np.radians(1.0)))
        other = (k + 1) % 3
        turned = np.cross(r0[:, other], r1[:, other]) @ r0[:, k]
        assert np.sign(turned) == (1 if sign == "+" else -1)
        drift = np.linalg.norm(end.gc[slot, 0] - start.gc[slot, 0]) * 1000.0
        assert drift < 3.0, (axis, sign, angle, drift)


def test_rotation_waypoints_are_the_reference_count():
    """ceil(angle / 10 deg) waypoints for every whole angle, in the planner's float32: 30, 60
    and 90 deg are not one more (90 deg's tenth waypoint, its end, would go unchecked)."""
    for deg in range(1, 91):
        rotvec = jnp.asarray([0.0, np.radians(deg), 0.0], jnp.float32)
        assert int(ctl.turn_waypoints(rotvec)) == -(-deg // 10), deg


def _turn(axis, angle_deg):
    """The right-hand rotation matrix by angle_deg about world axis x|y|z."""
    k = np.eye(3)[AXES[axis]]
    skew = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    t = np.radians(angle_deg)
    return np.eye(3) + np.sin(t) * skew + (1.0 - np.cos(t)) * skew @ skew


def test_world_rotation(home_batch):
    """A turn about a fixed world axis of a gripper whose axes are aligned with none of the
    world's: the orientation becomes R(e, t) R within 0.1 deg (the same turn about the local
    axis e would miss it by more than 10 deg), GC drifts under 0.5 mm."""
    cases = list(itertools.product("xyz", "+-", (10, 25, 45)))
    for tilt in ({"axis": "ry", "angle_deg": 25}, {"axis": "rx", "angle_deg": 20}):
        res = home_batch.step([{"action": "gripper.rotate_local", "sign": "+", **tilt}] * N_SLOTS)
        assert all(r.planner_success for r in res)
    start = home_batch.proprio()
    r0 = np.asarray(start.rot[0, 0], float)
    assert np.abs(r0).max(axis=0).max() < 0.97  # no local axis near a world axis
    results = home_batch.step(
        [
            {"action": "gripper.rotate_world", "axis": a, "sign": s, "angle_deg": d}
            for a, s, d in cases
        ]
    )
    end = home_batch.proprio()
    for slot, (axis, sign, angle) in enumerate(cases):
        res = results[slot]
        assert res.valid and res.planner_success and res.executed, (axis, sign, angle, res)
        assert res.label == f"rotate_world {axis}{sign}{angle}deg"
        r0, r1 = np.asarray(start.rot[slot, 0], float), np.asarray(end.rot[slot, 0], float)
        turn = _turn(axis, angle if sign == "+" else -angle)
        assert _rotation_angle_deg(turn @ r0, r1) < 0.1, (axis, sign, angle)
        assert _rotation_angle_deg(r0 @ turn, r1) > 10.0, (axis, sign, angle)
        drift = np.linalg.norm(end.gc[slot, 0] - start.gc[slot, 0]) * 1000.0
        assert drift < 0.5, (axis, sign, angle, drift)


def test_world_rotation_is_the_local_rotation_about_the_converted_axis(
    backend, batches, probe_task
):
    """At home the gripper's ry is world -x: a world x turn and the local ry turn of the
    opposite sign are one command, up to the float32 rounding of the converted axis (C MuJoCo:
    bit-identical; MJX: joints within 1e-6 rad, the cube within 2e-5, where the contact
    amplifies the rounding)."""
    batch = batches[0]
    q = probe_task.initial_qpos(batch.model, 0)
    batch.reset(range(N_SLOTS), np.broadcast_to(q, (N_SLOTS, batch.model.nq)), settle_steps=25)
    ry = np.asarray(batch.proprio().rot[0, 0], float)[:, 1]
    np.testing.assert_allclose(ry, [-1.0, 0.0, 0.0], atol=1e-6)
    pairs = [("+", "-", 30), ("-", "+", 20)]
    actions = [None] * N_SLOTS
    for i, (world_sign, local_sign, angle) in enumerate(pairs):
        actions[2 * i] = {"action": "gripper.rotate_world", "axis": "x", "sign": world_sign,
                          "angle_deg": angle}  # fmt: skip
        actions[2 * i + 1] = {"action": "gripper.rotate_local", "axis": "ry", "sign": local_sign,
                              "angle_deg": angle}  # fmt: skip
    results = batch.step(actions)
    assert all(r.planner_success for r in results if r is not None)
    qpos, arm = batch.qpos(), batch.layout.qpos.ravel()
    for i in range(len(pairs)):
        world, local = qpos[2 * i], qpos[2 * i + 1]
        np.testing.assert_allclose(world[arm], local[arm], rtol=0, atol=1e-6)
        np.testing.assert_allclose(world, local, rtol=0, atol=2e-5)
        if backend == "c":
            _assert_same_state(_state(batch, 2 * i), _state(batch, 2 * i + 1))
    assert np.abs(qpos[0][arm] - q[arm]).max() > 0.1  # it did turn


def test_world_rotation_out_of_bounds_is_refused_whole(single, probe_task, probe_model):
    """The control point at the top bound, GC below and in front of it: a world x turn that
    lifts the control point is refused at its first waypoint (valid, planner false, the slot
    bit-identical); the opposite turn, which lowers it, runs."""
    sb = _home_single(single, probe_task, probe_model)
    up = {"action": "gripper.move_world", "axis": "z", "sign": "+", "distance_mm": 100}
    for _ in range(4):
        res = sb.step([up])[0]
    assert res.clipped["right"] and sb.proprio().ee[0, 0][2] == pytest.approx(1.35, abs=2e-3)
    before = _state(sb)
    lift = {"action": "gripper.rotate_world", "axis": "x", "sign": "-", "angle_deg": 10}
    res = sb.step([lift])[0]
    assert res.valid and not res.planner_success and not res.executed
    _assert_same_state(before, _state(sb))
    res = sb.step([{**lift, "sign": "+"}])[0]
    assert res.valid and res.planner_success and res.executed


def _home_single(sb, task, model):
    sb.reset([0], task.initial_qpos(model, 0)[None], settle_steps=25)
    return sb


def test_unreachable_target_leaves_state_unchanged(single, probe_task, probe_model):
    """A move into the table and one out of reach both fail to plan; the slot is bit-identical."""
    sb = _home_single(single, probe_task, probe_model)
    down = {"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 100}
    assert sb.step([down])[0].planner_success
    before = _state(sb)
    result = sb.step([down])[0]
    assert result.valid and not result.planner_success and not result.executed
    _assert_same_state(before, _state(sb))
    # out of reach: far along +y, repeated until the planner refuses; the refusal moves nothing
    far = [{"action": "gripper.move_world", "axis": "y", "sign": "+", "distance_mm": 100}]
    for _ in range(6):
        snapshot = np.array(sb.qpos())
        res = sb.step(far)
        if not res[0].planner_success:
            np.testing.assert_array_equal(sb.qpos(), snapshot)
            break
    else:
        pytest.fail("600 mm along +y from home never failed to plan")


def test_workspace_clipping_is_reported(single, probe_task, probe_model):
    """A target beyond the end-effector bounds is clipped to them, and the result says so."""
    sb = _home_single(single, probe_task, probe_model)
    for _ in range(4):
        res = sb.step(
            [{"action": "gripper.move_world", "axis": "z", "sign": "+", "distance_mm": 100}]
        )
    assert res[0].clipped["right"] and res[0].planner_success
    assert res[0].executed_mm["right"] < 100.0
    ee = sb.proprio().ee[0, 0]
    assert ee[2] == pytest.approx(1.35, abs=2e-3)


def test_probe_cube_grasp_lift_hold(single, probe_task, probe_model):
    """Top-down approach, close, +100 mm: the cube rises >= 90 mm and slips < 5 mm in 1 s."""
    sb = single
    sb.reset(
        [0], probe_task.initial_qpos(probe_model, 7)[None], settle_steps=probe_task.settle_steps
    )
    cube0 = np.array(sb.object_poses(0)["cube"]["pos"])
    quat = sb.object_poses(0)["cube"]["quat"]
    yaw = np.degrees(2 * np.arctan2(quat[3], quat[0]))

    def act(**kw):
        res = sb.step([kw])[0]
        assert res.valid and res.planner_success, (kw, res)

    act(action="gripper.rotate_local", axis="ry", sign="+", angle_deg=40)  # approach down
    if abs(yaw) >= 1:  # fingers across the cube's faces
        act(
            action="gripper.rotate_local",
            axis="rx",
            sign="+" if yaw < 0 else "-",
            angle_deg=abs(yaw),
        )
    gc = sb.proprio().gc[0, 0]
    target = cube0 + [0.0, 0.0, 0.012]  # pads 12 mm above the cube's centre
    for axis in (0, 1, 2):
        d = (target[axis] - gc[axis]) * 1000.0
        while abs(d) >= 1:
            step = float(np.clip(d, -100.0, 100.0))
            act(
                action="gripper.move_world",
                axis="xyz"[axis],
                sign="+" if step > 0 else "-",
                distance_mm=abs(step),
            )
            d -= step
    act(action="gripper.close")
    act(action="gripper.move_world", axis="z", sign="+", distance_mm=100)
    cube1 = np.array(sb.object_poses(0)["cube"]["pos"])
    gc1 = sb.proprio().gc[0, 0]
    assert cube1[2] - cube0[2] >= 0.090
    sb.hold(int(round(1.0 / probe_model.opt.timestep)))
    cube2 = np.array(sb.object_poses(0)["cube"]["pos"])
    gc2 = sb.proprio().gc[0, 0]
    slip = np.linalg.norm((cube2 - gc2) - (cube1 - gc1))
    assert slip < 0.005
    assert cube2[2] - cube0[2] > 0.05 and not sb.grip_open()[0, 0]  # grasp_single_cube's terms


def test_determinism_across_batch_size_slot_and_neighbours(
    single, home_batch, probe_task, probe_model
):
    """The same slot state and action give bit-identical results whatever the batch size, the
    slot index and the other slots' actions."""
    action = {"action": "gripper.move_world", "axis": "y", "sign": "+", "distance_mm": 42}
    _home_single(single, probe_task, probe_model)
    single.step([action])
    reference = _state(single)
    neighbours = [
        {"action": "gripper.rotate_local", "axis": "rz", "sign": "-", "angle_deg": 30},
        {"action": "gripper.close"},
        None,
        {"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 80},
    ]
    for slot in (0, 11, N_SLOTS - 1):
        home_batch.reset(
            range(N_SLOTS),
            np.broadcast_to(probe_task.initial_qpos(probe_model, 0), (N_SLOTS, probe_model.nq)),
            25,
        )
        actions = [neighbours[(i + slot) % len(neighbours)] for i in range(N_SLOTS)]
        actions[slot] = action
        home_batch.step(actions)
        _assert_same_state(reference, _state(home_batch, slot))


@pytest.mark.parametrize(
    "action,field",
    [
        (
            {"action": "gripper.move_world", "axis": "z", "sign": "+", "distance_mm": 150},
            "distance_mm",
        ),
        (
            {"action": "gripper.move_world", "axis": "z", "sign": "+", "distance_mm": 0.5},
            "distance_mm",
        ),
        ({"action": "gripper.move_world", "axis": "w", "sign": "+", "distance_mm": 10}, "axis"),
        ({"action": "gripper.rotate_local", "axis": "x", "sign": "+", "angle_deg": 10}, "axis"),
        ({"action": "gripper.rotate_world", "axis": "rz", "sign": "+", "angle_deg": 10}, "axis"),
        (
            {"action": "gripper.rotate_world", "axis": "z", "sign": "+", "angle_deg": 0.5},
            "angle_deg",
        ),
        (
            {"action": "gripper.rotate_local", "axis": "rx", "sign": "+", "angle_deg": 91},
            "angle_deg",
        ),
        ({"action": "gripper.move_world", "axis": "z", "sign": "up", "distance_mm": 10}, "sign"),
        ({"action": "gripper.fly"}, "action"),
        ({"action": "dual_gripper.close"}, "action"),  # dual action in a single-arm task
        (
            {
                "action": "gripper.move_world",
                "axis": "z",
                "sign": "+",
                "distance_mm": 10,
                "arm": "left",
            },
            "arm",
        ),
    ],
)
def test_bad_action_rejected_without_touching_state(single, action, field):
    before = _state(single)
    result = single.step([action])[0]
    assert not result.valid and not result.executed
    assert f"field '{field}'" in result.error
    _assert_same_state(before, _state(single))
