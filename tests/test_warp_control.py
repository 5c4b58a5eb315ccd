"""The Warp port of the executor (`warp.fk_ik`, `warp.arm_indices`, `warp.control`) against its
JAX original, on Warp's CPU device.

The JAX kinematics and planner are the oracle here (they are themselves tested against C MuJoCo
in test_kinematics.py): forward kinematics, gripper points and proprioception, the IK and its
branch choice, the plan of random commands flag for flag, and the joint references of a plan.
Both sides compute in float32 with the same formulas but not the same libm (XLA's atan2 / sin
approximations against the C library's), so values agree to rounding, and a discrete decision
agrees except where the input sits on its threshold to within that rounding. Such knife-edge
cases are detected on the JAX side alone (its decisions change under a 1e-5 perturbation of the
input: `_ik_stable`, `_plan_stable`) and left out; the assertions bound how many may be.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

wp = pytest.importorskip("warp", reason="the Warp port needs warp-lang (the [test] extra has it)")

from vabench.sim_mjx import controller as ctl  # noqa: E402
from vabench.sim_mjx import kinematics as kin  # noqa: E402
from vabench.sim_mjx import layout as lay  # noqa: E402
from vabench.sim_mjx import robot_constants as rc  # noqa: E402
from vabench.sim_mjx import scene  # noqa: E402
from vabench.sim_mjx.warp import arm_indices as wl  # noqa: E402
from vabench.sim_mjx.warp import control as wc  # noqa: E402
from vabench.sim_mjx.warp import fk_ik as wk  # noqa: E402

wp.config.quiet = True  # Warp < 1.10
wp.config.log_level = getattr(wp, "LOG_WARNING", 30)  # Warp >= 1.10: no "Module ... load" lines

# Tolerances: float32 through ~1 m of chain, and through the closed-form IK (angles).
POS_TOL = 1e-5
ANGLE_TOL = 1e-4
N_SUBSTEPS = 200
FLOOR_Z = rc.TABLE_Z + rc.TABLE_CLEARANCE


@pytest.fixture(scope="module", autouse=True)
def _cpu():
    with wp.ScopedDevice("cpu"):
        yield


@pytest.fixture(scope="module")
def dual():
    m = scene.build_model(("left", "right"))
    layout = lay.ArmLayout.from_model(m)
    geoms = layout.geometry(m)
    return m, layout, geoms, wk.arm_geometries(geoms, "cpu"), wl.layout_arrays(layout, "cpu")


def _front_q(rng: np.random.Generator, n: int, geoms: kin.ArmGeometry) -> np.ndarray:
    """(n, A, 6) joint angles with the wrist in front of the waist (the branch the IK solves)."""
    lo, hi = np.asarray(geoms.q_lo), np.asarray(geoms.q_hi)
    q = rng.uniform(0.8 * lo, 0.8 * hi, (n, *lo.shape))
    q[..., 1] = rng.uniform(-0.6, 1.2, q.shape[:-1])
    q[..., 2] = rng.uniform(-0.8, 1.2, q.shape[:-1])
    return q.astype(np.float32)


def _qpos(m, layout: lay.ArmLayout, q: np.ndarray, fingers: np.ndarray) -> np.ndarray:
    qpos = np.tile(scene.home_qpos(m), (len(q), 1)).astype(np.float32)
    qpos[:, layout.qpos] = q
    qpos[:, layout.fingers] = fingers
    return qpos


# -- kinematics ------------------------------------------------------------------------------


@wp.kernel
def _kinematics_kernel(
    geoms: wp.array(dtype=wk.ArmGeometryW),
    q: wp.array2d(dtype=wk.vec6),
    fingers: wp.array2d(dtype=wp.vec2),
    rotvec: wp.array2d(dtype=wp.vec3),
    wrist: wp.array2d(dtype=wp.vec3),
    rot: wp.array2d(dtype=wp.mat33),
    ee: wp.array2d(dtype=wp.vec3),
    gc: wp.array2d(dtype=wp.vec3),
    low: wp.array2d(dtype=float),
    exp: wp.array2d(dtype=wp.mat33),
):
    n, a = wp.tid()
    g = geoms[a]
    w, r = wk.fk(g, q[n, a])
    wrist[n, a] = w
    rot[n, a] = r
    e, _r, c = wk.gripper_points(g, q[n, a], fingers[n, a])
    ee[n, a] = e
    gc[n, a] = c
    low[n, a] = wk.lowest_gripper_z(g, q[n, a], fingers[n, a])
    exp[n, a] = wk.axis_angle(rotvec[n, a])


def test_fk_gripper_points_and_boxes(dual):
    _, _, geoms, wgeoms, _ = dual
    rng = np.random.default_rng(3)
    n = 200
    lo, hi = np.asarray(geoms.q_lo), np.asarray(geoms.q_hi)
    q = rng.uniform(lo, hi, (n, *lo.shape)).astype(np.float32)
    fingers = rng.uniform(0.0, rc.FINGER_OPEN, (n, 2, 2)).astype(np.float32)
    rotvec = rng.normal(0.0, 1.0, (n, 2, 3)).astype(np.float32)
    rotvec[:10] = 0.0  # Rodrigues at zero is the identity, exactly

    arrays = [wp.array(x, dtype=t) for x, t in ((q, wk.vec6), (fingers, wp.vec2))]
    arrays.append(wp.array(rotvec, dtype=wp.vec3))
    out = [wp.zeros((n, 2), dtype=t) for t in (wp.vec3, wp.mat33, wp.vec3, wp.vec3, float)]
    out.append(wp.zeros((n, 2), dtype=wp.mat33))
    wp.launch(_kinematics_kernel, dim=(n, 2), inputs=[wgeoms, *arrays], outputs=out)
    wrist, rot, ee, gc, low, exp = (a.numpy() for a in out)

    def jax_side(g, q, f):
        return (*kin.fk(g, q), *kin.gripper_points(g, q, f), kin.lowest_gripper_z(g, q, f))

    ref = jax.jit(jax.vmap(jax.vmap(jax_side), in_axes=(None, 0, 0)))(geoms, q, fingers)
    ref_exp = jax.vmap(jax.vmap(kin.axis_angle))(rotvec)
    for got, want in zip((wrist, rot, ee, rot, gc, low), ref, strict=True):
        np.testing.assert_allclose(got, want, atol=POS_TOL)
    np.testing.assert_allclose(exp, ref_exp, atol=POS_TOL)
    np.testing.assert_array_equal(exp[:10], np.broadcast_to(np.eye(3), (10, 2, 3, 3)))


def test_proprio_matches_proprio_slot(dual):
    m, layout, geoms, wgeoms, idx = dual
    rng = np.random.default_rng(4)
    n = 256
    lo, hi = np.asarray(geoms.q_lo), np.asarray(geoms.q_hi)
    q = rng.uniform(lo, hi, (n, *lo.shape)).astype(np.float32)
    qpos = _qpos(m, layout, q, rng.uniform(0.0, rc.FINGER_OPEN, (n, 2, 2)))
    grip = rng.integers(0, 2, (n, 2)).astype(np.int32)
    obs = wl.ProprioBuffers.allocate(n, 2, "cpu")
    wl.launch_proprio(wgeoms, wp.array(qpos, dtype=float), idx, obs, wp.array(grip, dtype=int))

    want = jax.jit(jax.vmap(lambda qp, g: lay.proprio_slot(layout, geoms, qp, g)))(qpos, grip)
    for name in ("gc", "ee", "rot", "fingers"):
        np.testing.assert_allclose(getattr(obs, name).numpy(), getattr(want, name), atol=POS_TOL)
    # Knife edges of the representation, not of the port: atan2 jumps by 2 pi where its first
    # argument crosses zero with the second negative, and q and -q are one rotation where w = 0.
    r = np.asarray(want.rot)
    edge = (np.abs(r[..., 2, 1]) < 1e-5) & (r[..., 2, 2] < 0)
    edge |= (np.abs(r[..., 1, 0]) < 1e-5) & (r[..., 0, 0] < 0)
    edge |= np.abs(np.asarray(want.quat)[..., 0]) < 1e-5
    assert edge.sum() <= 2
    keep = ~edge
    np.testing.assert_allclose(obs.quat.numpy()[keep], np.asarray(want.quat)[keep], atol=POS_TOL)
    np.testing.assert_allclose(obs.rpy.numpy()[keep], np.asarray(want.rpy)[keep], atol=POS_TOL)


# -- inverse kinematics ----------------------------------------------------------------------


@wp.kernel
def _ik_kernel(
    geoms: wp.array(dtype=wk.ArmGeometryW),
    ee: wp.array2d(dtype=wp.vec3),
    rot: wp.array2d(dtype=wp.mat33),
    q_prev: wp.array2d(dtype=wk.vec6),
    q: wp.array2d(dtype=wk.vec6),
    ok: wp.array2d(dtype=int),
):
    n, a = wp.tid()
    qn, okn = wk.ik(geoms[a], ee[n, a], rot[n, a], q_prev[n, a])
    q[n, a] = qn
    ok[n, a] = wp.where(okn, 1, 0)


def _warp_ik(wgeoms, ee, rot, q_prev):
    n = len(ee)
    q, ok = wp.zeros((n, 2), dtype=wk.vec6), wp.zeros((n, 2), dtype=int)
    inputs = [wp.array(ee, dtype=wp.vec3), wp.array(rot, dtype=wp.mat33)]
    wp.launch(
        _ik_kernel,
        dim=(n, 2),
        inputs=[wgeoms, *inputs, wp.array(q_prev, dtype=wk.vec6)],
        outputs=[q, ok],
    )
    return q.numpy(), ok.numpy().astype(bool)


def test_ik_round_trip_and_branch(dual):
    _, _, geoms, wgeoms, _ = dual
    rng = np.random.default_rng(5)
    n = 300
    q = _front_q(rng, n, geoms)
    # The wrist away from its singularity (pitch 0), where rounding decides the two rolls.
    q[..., 4] = np.where(q[..., 4] < 0, -1, 1) * np.maximum(np.abs(q[..., 4]), 0.2)
    points = jax.jit(jax.vmap(jax.vmap(kin.gripper_points), in_axes=(None, 0, None)))
    ee, rot, _ = points(geoms, q, jnp.zeros((2, 2)))
    ee, rot = np.array(ee), np.asarray(rot)
    # q_prev near the solution, or with the wrist half a turn away (the other branch nearer),
    # or far off; some targets pushed out of reach.
    noise = rng.normal(0.0, 0.05, q.shape)
    flip = rng.random(n) < 0.3
    noise[flip, :, 3] += np.pi
    noise[flip, :, 5] += np.pi
    far_off = rng.random(n) < 0.2
    noise[far_off] += rng.normal(0.0, 1.0, (far_off.sum(), 2, 6))
    q_prev = (q + noise).astype(np.float32)
    far = rng.random(n) < 0.15
    ee[far] += np.array([0.0, 0.5, 0.0], np.float32)

    jax_ik = jax.jit(jax.vmap(jax.vmap(kin.ik), in_axes=(None, 0, 0, 0)))
    want_q, want_ok = (np.asarray(x) for x in jax_ik(geoms, ee, rot, q_prev))
    got_q, got_ok = _warp_ik(wgeoms, ee, rot, q_prev)
    stable = _ik_stable(jax_ik, geoms, ee, rot, q_prev, want_q, want_ok, rng)
    assert stable.mean() > 0.97, stable.mean()
    np.testing.assert_array_equal(got_ok[stable], want_ok[stable])
    both = stable & want_ok
    assert both.sum() > 300 and (stable & ~want_ok).sum() > 30
    np.testing.assert_allclose(got_q[both], want_q[both], atol=ANGLE_TOL)  # the same branch
    took_flip = np.abs(want_q[..., 3] - q[..., 3]) > 1.0
    assert (both & took_flip).sum() > 20  # the second branch was exercised
    got_ee, got_rot, _ = points(geoms, got_q, jnp.zeros((2, 2)))
    np.testing.assert_allclose(np.asarray(got_ee)[both], ee[both], atol=POS_TOL)
    np.testing.assert_allclose(np.asarray(got_rot)[both], rot[both], atol=POS_TOL)


def _ik_stable(jax_ik, geoms, ee, rot, q_prev, want_q, want_ok, rng):
    """Cases whose JAX answer is the same under +-1e-5 perturbations of ee and q_prev: no
    threshold (reach, limits, branch distance, angle wrap) lies within that of the input."""
    stable = np.ones(want_ok.shape, bool)
    for _ in range(2):
        d_ee = rng.normal(0.0, 1.0, ee.shape)
        d_q = rng.normal(0.0, 1.0, q_prev.shape)
        for sign in (-1e-5, 1e-5):
            q2, ok2 = jax_ik(geoms, ee + sign * d_ee, rot, q_prev + sign * d_q)
            jump = np.abs(np.asarray(q2) - want_q).max(-1) > 1e-3
            stable &= (np.asarray(ok2) == want_ok) & ~(jump & want_ok)
    return stable


# -- the plan --------------------------------------------------------------------------------


def _commands(rng: np.random.Generator, n: int):
    """Random per-arm commands: world translations (1..100 mm along an axis), rotations
    (1..90 deg about a local axis), or none; each with a random gripper command."""
    delta = np.zeros((n, 2, 3), np.float32)
    rotvec = np.zeros((n, 2, 3), np.float32)
    kind = rng.choice(3, (n, 2), p=[0.45, 0.35, 0.2])
    axis = rng.integers(0, 3, (n, 2))
    sign = rng.choice([-1.0, 1.0], (n, 2))
    mm = rng.uniform(*rc.MOVE_MM_RANGE, (n, 2)) / 1000.0
    rad = np.radians(rng.uniform(*rc.ROTATE_DEG_RANGE, (n, 2)))
    for s, a in np.ndindex(n, 2):
        if kind[s, a] == 0:
            delta[s, a, axis[s, a]] = sign[s, a] * mm[s, a]
        elif kind[s, a] == 1:
            rotvec[s, a, axis[s, a]] = sign[s, a] * rad[s, a]
    grip = rng.choice([ctl.GRIP_KEEP, ctl.GRIP_CLOSE, ctl.GRIP_OPEN], (n, 2)).astype(np.int32)
    return delta, rotvec, grip


def _states(rng: np.random.Generator, n: int, m, layout, geoms):
    """qpos and held controls: near home (most plans succeed), anywhere in front of the waist
    (plans that clip or go into the table), or with the arm nearly stretched (out of reach)."""
    home = np.asarray(rc.HOME_Q, np.float32) + rng.normal(0.0, 0.25, (n, 2, 6))
    stretched = _front_q(rng, n, geoms)
    stretched[..., 2] = rng.uniform(-1.5, -0.9, (n, 2))  # elbow -pi/2: the arm straight
    family = rng.choice(3, n, p=[0.4, 0.35, 0.25])[:, None, None]
    q = np.select([family == 0, family == 1], [home, _front_q(rng, n, geoms)], stretched)
    q = q.astype(np.float32)
    fingers = rng.uniform(0.0, rc.FINGER_OPEN, (n, 2, 2)).astype(np.float32)
    qpos = _qpos(m, layout, q, fingers)
    ctrl = layout.reset_ctrl(np.zeros((n, m.nu), np.float32), qpos)
    ctrl[:, layout.arm_act] += rng.normal(0.0, 0.01, (n, 2, 6))
    ctrl[:, layout.finger_act] = rng.uniform(0.0, rc.FINGER_OPEN, (n, 2, 2))
    return qpos, ctrl.astype(np.float32)


def _warp_plan(dual, qpos, ctrl, active, delta, rotvec, grip, paced=False):
    """The Warp kernels' plan of these slots: (PlanBuffers, ok, go)."""
    _, _, _, wgeoms, idx = dual
    n = len(qpos)
    plan = wc.PlanBuffers.allocate(n, 2, "cpu")
    ok, go = wp.zeros(n, dtype=int), wp.zeros(n, dtype=int)
    wc.launch_plan(
        wgeoms,
        wp.array(qpos, dtype=float),
        wp.array(ctrl, dtype=float),
        idx,
        wp.array(active, dtype=int),
        wp.array(delta, dtype=wp.vec3),
        wp.array(rotvec, dtype=wp.vec3),
        wp.array(grip, dtype=int),
        plan,
        ok,
        go,
        N_SUBSTEPS,
        ctl.rest_from(N_SUBSTEPS),
        paced=paced,
    )
    return plan, ok, go


@pytest.fixture(scope="module")
def plans(dual):
    """A few hundred random (state, command) slots, planned by JAX and by the Warp kernels
    (paced timing: `test_fixed_timing` covers the other)."""
    m, layout, geoms, _, _ = dual
    rng = np.random.default_rng(6)
    n = 300
    qpos, ctrl = _states(rng, n, m, layout, geoms)
    delta, rotvec, grip = _commands(rng, n)
    active = (rng.random(n) < 0.9).astype(np.int32)

    def plan_one(qp, c, d, rv, g):
        cmd = ctl.ArmCommand(active=jnp.array(True), delta=d, rotvec=rv, grip=g)
        return lay.plan_from(layout, geoms, qp, c, cmd, N_SUBSTEPS, paced=True)

    jax_plan = jax.jit(jax.vmap(plan_one))
    want = jax_plan(qpos, ctrl, delta, rotvec, grip)

    plan, ok, go = _warp_plan(dual, qpos, ctrl, active, delta, rotvec, grip, paced=True)
    got = {k: getattr(plan, k).numpy() for k in vars(plan)}
    got.update(ok=ok.numpy(), go=go.numpy(), active=active)
    stable = _plan_stable(jax_plan, want, rng, qpos, ctrl, delta, rotvec, grip, layout)
    case = {"qpos": qpos, "ctrl": ctrl, "delta": delta, "rotvec": rotvec, "grip": grip}
    return case, jax.tree.map(np.asarray, want), got, stable


def _plan_stable(jax_plan, want, rng, qpos, ctrl, delta, rotvec, grip, layout):
    """(N, A): arms whose JAX plan keeps its flags, and its waypoints where it succeeds, under
    +-1e-5 perturbations of the measured joints and fingers. An arm within rounding of a
    threshold (reach, a joint limit, the wrist-flip step, the table, the workspace bounds, a
    branch or wrap choice) changes its JAX answer under one of each antithetic pair."""
    adr = np.concatenate([layout.qpos, layout.fingers], axis=1)  # (A, 8)
    ok, clipped = np.asarray(want.arm_ok), np.asarray(want.clipped)
    wps = np.asarray(want.waypoints)
    stable = np.ones(ok.shape, bool)
    for _ in range(2):
        d = np.zeros_like(qpos)
        d[:, adr] = rng.normal(0.0, 1.0, (len(qpos), *adr.shape))
        for sign in (-1e-5, 1e-5):
            other = jax_plan(qpos + sign * d, ctrl, delta, rotvec, grip)
            jump = np.abs(np.asarray(other.waypoints) - wps).max((-1, -2)) > 1e-3
            stable &= (np.asarray(other.arm_ok) == ok) & (np.asarray(other.clipped) == clipped)
            stable &= ~(jump & ok)
    return stable


def test_plan_flags_match(plans):
    _, want, got, stable = plans
    assert stable.mean() > 0.97, stable.mean()
    np.testing.assert_array_equal(got["moves"], want.moves)
    np.testing.assert_array_equal(got["arm_ok"][stable], want.arm_ok[stable])
    np.testing.assert_array_equal(got["clipped"][stable], want.clipped[stable])
    slot_stable = stable.all(1)
    np.testing.assert_array_equal(got["ok"][slot_stable], want.ok[slot_stable])
    np.testing.assert_array_equal(got["go"], got["ok"] & got["active"])
    np.testing.assert_array_equal(got["hold"], want.hold)
    np.testing.assert_array_equal(got["finger_start"], want.finger_start)
    np.testing.assert_array_equal(got["finger_target"], want.finger_target)


def test_plan_waypoints_match(plans):
    _, want, got, stable = plans
    ok = stable & want.arm_ok
    np.testing.assert_allclose(got["waypoints"][ok], want.waypoints[ok], atol=ANGLE_TOL)
    np.testing.assert_allclose(got["executed_m"][ok], want.executed_m[ok], atol=ANGLE_TOL)
    still = ~want.moves
    np.testing.assert_array_equal(got["waypoints"][still], want.waypoints[still])
    np.testing.assert_array_equal(got["executed_m"][still], 0.0)


def test_plan_timing_matches(plans):
    """Paced timing: each arm's move and ramp substeps, and the slot's final substep, as JAX's;
    short moves faster, none slower than the fixed timing's."""
    _, want, got, stable = plans
    ok = stable & want.arm_ok
    np.testing.assert_allclose(got["move_steps"][ok], want.move_steps[ok], rtol=1e-5)
    np.testing.assert_array_equal(got["grip_steps"], want.grip_steps)
    slot = stable.all(1)
    assert np.abs(got["rest_from"][slot] - want.rest_from[slot]).max() <= 1
    assert (got["rest_from"][slot] == want.rest_from[slot]).mean() > 0.99
    full = rc.MOVE_FRACTION * N_SUBSTEPS
    moving = want.moves & ok
    assert (want.move_steps[moving] < full - 1).sum() >= 10
    assert (want.move_steps <= full + 1e-4).all()
    assert (want.move_steps >= rc.PACE_MIN * full - 1e-4).all()
    assert (want.rest_from >= 1).all() and (want.rest_from <= ctl.rest_from(N_SUBSTEPS)).all()


def test_fixed_timing(dual):
    """Fixed timing: every action's move, ramp and final substep those of ACTION_SECONDS."""
    m, layout, geoms, _, _ = dual
    rng = np.random.default_rng(8)
    n = 20
    qpos, ctrl = _states(rng, n, m, layout, geoms)
    delta, rotvec, grip = _commands(rng, n)
    plan, _, _ = _warp_plan(dual, qpos, ctrl, np.ones(n, np.int32), delta, rotvec, grip)
    cmd = ctl.ArmCommand(active=jnp.array(True), delta=delta[0], rotvec=rotvec[0], grip=grip[0])
    want = lay.plan_from(layout, geoms, qpos[0], ctrl[0], cmd, N_SUBSTEPS)
    for got, expected in (
        (plan.move_steps.numpy(), rc.MOVE_FRACTION * N_SUBSTEPS),
        (plan.grip_steps.numpy(), rc.GRIP_FRACTION * N_SUBSTEPS),
        (plan.rest_from.numpy(), ctl.rest_from(N_SUBSTEPS)),
    ):
        np.testing.assert_array_equal(got, np.float32(expected))
    np.testing.assert_array_equal(want.move_steps, np.float32(rc.MOVE_FRACTION * N_SUBSTEPS))
    assert int(want.rest_from) == ctl.rest_from(N_SUBSTEPS)


def test_plan_cases_cover_every_outcome(plans, dual):
    """The random cases include plans that succeed, clip, leave the reach and hit the table
    (the flags test compares the port on all of them)."""
    _, layout, geoms, _, _ = dual
    case, want, _, stable = plans
    moving = want.moves & stable
    # A translation keeps the rotation and moves every point by the same (clipped) step, so
    # its reach and table outcomes follow from the start pose.
    translate = moving & (np.abs(case["rotvec"]).max(-1) == 0)
    q, fingers = case["qpos"][:, layout.qpos], case["qpos"][:, layout.fingers]
    ee, _, _ = jax.vmap(jax.vmap(kin.gripper_points), in_axes=(None, 0, 0))(geoms, q, fingers)
    wrist, _ = jax.vmap(jax.vmap(kin.fk), in_axes=(None, 0))(geoms, q)
    low = jax.vmap(jax.vmap(kin.lowest_gripper_z), in_axes=(None, 0, 0))(geoms, q, fingers)
    ee = np.asarray(ee)
    step = np.clip(ee + case["delta"], rc.EE_BOUNDS_LO, rc.EE_BOUNDS_HI) - ee
    shoulder = np.asarray(geoms.base_pos).copy()
    shoulder[:, 2] += np.asarray(geoms.shoulder_height)
    reach = np.asarray(geoms.upper_arm + geoms.forearm)
    end = np.asarray(wrist) + step
    out_of_reach = translate & (np.linalg.norm(end - shoulder, axis=-1) > reach + 1e-3)
    into_table = translate & (np.asarray(low) + step[..., 2] < FLOOR_Z - 1e-3)
    counts = {
        "ok": (moving & want.arm_ok).sum(),
        "failed": (moving & ~want.arm_ok).sum(),
        "clipped": (moving & want.clipped).sum(),
        "out of reach": out_of_reach.sum(),
        "into the table": (into_table & ~out_of_reach).sum(),
    }
    assert min(counts.values()) >= 5, counts
    assert not want.arm_ok[out_of_reach | into_table].any()


# -- references and the slot flags -----------------------------------------------------------


@pytest.mark.parametrize("k", [0, 1, N_SUBSTEPS // 2, 139, N_SUBSTEPS - 1])
def test_ctrl_matches_ctrl_at(plans, dual, k):
    """The references of substep k from the same (JAX) plan; controls other than the arms'
    and fingers' (three extra columns here) keep their values."""
    _, layout, _, _, idx = dual
    case, want, _, _ = plans
    n = len(case["ctrl"])
    plan = wc.PlanBuffers.allocate(n, 2, "cpu")
    for name in ("waypoints", "hold", "finger_start", "finger_target", "move_steps", "grip_steps"):
        getattr(plan, name).assign(np.asarray(getattr(want, name), np.float32))
    plan.moves.assign(want.moves.astype(np.int32))
    extra = np.random.default_rng(k).normal(0.0, 1.0, (n, 3)).astype(np.float32)
    base = np.concatenate([case["ctrl"] + np.float32(7.0), extra], axis=1)
    ctrl = wp.array(base, dtype=float)
    wc.launch_ctrl(wp.array([k], dtype=int), plan, idx, ctrl)  # a device counter

    def refs(p, c):
        return lay.with_refs(layout, c, *ctl.ctrl_at(p, jnp.asarray(k)))

    expected = jax.vmap(refs)(jax.tree.map(jnp.asarray, want), base)
    np.testing.assert_allclose(ctrl.numpy(), expected, atol=2e-6)
    np.testing.assert_array_equal(ctrl.numpy()[:, -3:], extra)


def test_slot_flags():
    arm_ok = np.array([[1, 1], [1, 0], [0, 0], [1, 1]], np.int32)
    active = np.array([1, 1, 1, 0], np.int32)
    ok, go = wp.zeros(4, dtype=int), wp.zeros(4, dtype=int)
    wp.launch(
        wc.slot_ok_kernel,
        dim=4,
        inputs=[wp.array(arm_ok, dtype=int), wp.array(active, dtype=int)],
        outputs=[ok, go],
    )
    np.testing.assert_array_equal(ok.numpy(), [1, 0, 0, 1])
    np.testing.assert_array_equal(go.numpy(), [1, 0, 0, 0])
