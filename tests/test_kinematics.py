"""Closed-form kinematics against C MuJoCo (the oracle), and reachability of the paper's ranges."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from vabench.sim_mjx import kinematics as kin
from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx import scene

# float32 forward kinematics over ~1 m of chain: rounding stays well under a micrometre.
FK_TOL = 2e-6


@pytest.fixture(scope="module")
def dual():
    m = scene.build_model(("left", "right"))
    return m, mujoco.MjData(m)


def _random_front_q(rng, g):
    """Joint angles with the wrist in front of the waist (the branch the IK solves)."""
    lo, hi = np.array(g.q_lo), np.array(g.q_hi)
    q = rng.uniform(lo * 0.8, hi * 0.8)
    q[1] = rng.uniform(-0.6, 1.2)  # shoulder
    q[2] = rng.uniform(-0.8, 1.2)  # elbow
    return q


@pytest.mark.parametrize("arm", rc.ARMS)
def test_fk_matches_mujoco(dual, arm):
    m, d = dual
    g = kin.ArmGeometry.from_model(m, f"{arm}_")
    rng = np.random.default_rng(1)
    adr = [m.joint(f"{arm}_{j}").qposadr[0] for j in rc.ARM_JOINTS]
    fadr = [m.joint(f"{arm}_{j}").qposadr[0] for j in rc.FINGER_JOINTS]
    for _ in range(25):
        q = rng.uniform(np.array(g.q_lo), np.array(g.q_hi))
        f = rng.uniform(0, rc.FINGER_OPEN, 2)
        d.qpos[adr], d.qpos[fadr] = q, f
        mujoco.mj_kinematics(m, d)
        ee, rot, gc = kin.gripper_points(
            g, jnp.asarray(q, jnp.float32), jnp.asarray(f, jnp.float32)
        )
        np.testing.assert_allclose(ee, d.site(f"{arm}_ee").xpos, atol=FK_TOL)
        np.testing.assert_allclose(rot, d.site(f"{arm}_ee").xmat.reshape(3, 3), atol=FK_TOL)
        pads = 0.5 * (d.site(f"{arm}_pad_a").xpos + d.site(f"{arm}_pad_b").xpos)
        np.testing.assert_allclose(gc, pads, atol=FK_TOL)


def test_gripper_boxes_match_model(dual):
    m, _ = dual
    for name, (centre, half) in (
        ("palm", rc.PALM_BOX),
        ("finger_a", rc.FINGER_A_BOX),
        ("finger_b", rc.FINGER_B_BOX),
    ):
        gid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"right_{name}")
        np.testing.assert_allclose(m.geom_size[gid], half)
        np.testing.assert_allclose(m.geom_pos[gid], centre)


def test_ik_round_trip(dual):
    m, _ = dual
    g = kin.ArmGeometry.from_model(m, "right_")
    rng = np.random.default_rng(2)
    ik = jax.jit(kin.ik)
    for _ in range(40):
        q = _random_front_q(rng, g)
        ee, rot, _ = kin.gripper_points(g, jnp.asarray(q), jnp.zeros(2))
        q_sol, ok = ik(g, ee, rot, jnp.asarray(q + rng.normal(0, 0.05, 6)))
        assert ok
        ee2, rot2, _ = kin.gripper_points(g, q_sol, jnp.zeros(2))
        np.testing.assert_allclose(ee2, ee, atol=1e-5)
        np.testing.assert_allclose(rot2, rot, atol=1e-5)


def test_ik_reports_unreachable(dual):
    m, _ = dual
    g = kin.ArmGeometry.from_model(m, "right_")
    _, ok = kin.ik(g, jnp.array([0.28, 0.6, 0.9]), jnp.eye(3), jnp.zeros(6))
    assert not ok


# Object regions of the paper's appendix tables (x range, y range) with a grasp height for GC,
# and the shared regions both arms must reach (handover midline, pot handles, shoe mat).
RIGHT_ARM_REGIONS = {
    "grasp_single_bottle": ((0.20, 0.28), (-0.16, -0.04), 0.80),
    "grasp_single_cube": ((0.18, 0.26), (-0.16, -0.06), 0.78),
    "grasp_single_pen": ((0.18, 0.26), (-0.20, -0.10), 0.76),
    "grasp_pen_leaning_cube": ((0.16, 0.22), (-0.24, -0.20), 0.77),
    "click_bell_right": ((0.12, 0.26), (-0.18, -0.04), 0.80),
    "beat_block_hammer_right.hammer": ((0.02, 0.06), (-0.10, -0.04), 0.77),
    "beat_block_hammer_right.block": ((0.14, 0.22), (0.06, 0.13), 0.80),
    "place_cube_in_bowl.bowl": ((0.10, 0.14), (0.0, 0.04), 0.80),
    "place_single_bottle_upright.target": ((0.03, 0.09), (0.07, 0.13), 0.82),
}
BOTH_ARM_REGIONS = {
    "handover_midline": ((-0.05, 0.05), (-0.05, 0.0), 0.95),
    "place_shoe.mat": ((-0.05, 0.05), (-0.10, -0.06), 0.80),
    # Regions each arm works on its own side: x given for the right arm, mirrored for the left.
    "handover_horizontal_block.giver": ((0.15, 0.20), (-0.05, 0.0), 0.76),
    "lift_pot.handle": ((0.07, 0.17), (-0.05, 0.05), 0.84),
    "place_shoe.shoe": ((0.15, 0.25), (-0.10, 0.05), 0.78),
}
MIRRORED = {"handover_horizontal_block.giver", "lift_pot.handle", "place_shoe.shoe"}


def _top_down(yaw):
    rx = np.array([0.0, 0.0, -1.0])
    ry = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    return np.stack([rx, ry, np.cross(rx, ry)], 1)


def _side(angle):
    rx = np.array([np.sin(angle), np.cos(angle), 0.0])
    rz = np.array([0.0, 0.0, 1.0])
    return np.stack([rx, np.cross(rz, rx), rz], 1)


def _reachable(g, gc, rot):
    ee = gc - rot[:, 0] * (rc.PAD_X - rc.EE_SITE_X)
    q, ok = kin.ik(g, jnp.asarray(ee), jnp.asarray(rot), jnp.asarray(rc.HOME_Q))
    low = kin.lowest_gripper_z(g, q, jnp.full(2, rc.FINGER_OPEN))
    return bool(ok) and float(low) >= rc.TABLE_Z


@pytest.mark.parametrize(
    "region,arms",
    [(r, ("right",)) for r in RIGHT_ARM_REGIONS] + [(r, rc.ARMS) for r in BOTH_ARM_REGIONS],
)
def test_paper_ranges_reachable_top_down_and_side(dual, region, arms):
    m, _ = dual
    (xr, yr, z) = {**RIGHT_ARM_REGIONS, **BOTH_ARM_REGIONS}[region]
    for arm in arms:
        g = kin.ArmGeometry.from_model(m, f"{arm}_")
        x_range = (-xr[1], -xr[0]) if arm == "left" and region in MIRRORED else xr
        for x, y in itertools.product(np.linspace(*x_range, 3), np.linspace(*yr, 3)):
            gc = np.array([x, y, z])
            for yaw in np.radians([-90, -45, 0, 45, 90]):
                assert _reachable(g, gc, _top_down(yaw)), (region, arm, gc, "top-down", yaw)
            side_ok = [_reachable(g, gc + [0, 0, 0.02], _side(a)) for a in np.radians([-30, 0, 30])]
            assert any(side_ok), (region, arm, gc, "side")
