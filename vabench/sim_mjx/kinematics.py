"""Closed-form forward and inverse kinematics of one vabench arm, in JAX.

The arm (assets/robot/arm.xml) is waist(z) - shoulder(y) - elbow(y) - forearm roll(x) -
wrist pitch(y) - wrist roll(x), with no offsets between the shoulder and the waist axis and a
spherical wrist: the last three axes meet at the wrist centre. So the wrist centre fixes the
first three joints (a planar two-link problem after the waist angle) and the gripper rotation
fixes the last three as an x-y-x Euler decomposition. Both are exact, branch-free to trace and
cheap enough to solve at every waypoint of every slot.

Conventions: the gripper rotation R has columns (rx, ry, rz) = approach, finger-closing and
palm-side axes in the world frame. All functions act on one arm; the batch vmaps them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import jax_setup  # noqa: F401  (JAX configured before it compiles)
from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx.pytree import PyTree, pytree_dataclass

_TWO_PI = 2.0 * np.pi
_LIMIT_TOL = 1e-6


@pytree_dataclass
class ArmGeometry(PyTree):
    """Kinematic parameters of one arm, read from the compiled model."""

    base_pos: jax.Array  # (3,) world position of the base frame
    base_rot: jax.Array  # (3, 3) world rotation of the base frame
    shoulder_height: jax.Array  # shoulder axis above the base origin
    upper_arm: jax.Array  # shoulder -> elbow
    forearm: jax.Array  # elbow -> wrist centre
    q_lo: jax.Array  # (6,) joint lower limits
    q_hi: jax.Array  # (6,) joint upper limits

    @staticmethod
    def from_model(m: mujoco.MjModel, prefix: str) -> ArmGeometry:
        def body(name: str) -> int:
            return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, prefix + name)

        base = body("base")
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, m.body_quat[base])
        # The base hangs from the world, so its body frame is its world frame.
        shoulder = m.body_pos[body("waist")][2] + m.body_pos[body("upper_arm")][2]
        forearm = m.body_pos[body("forearm_roll")][0] + m.body_pos[body("wrist")][0]
        jids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, prefix + j) for j in rc.ARM_JOINTS]
        rng = m.jnt_range[jids]
        return ArmGeometry(
            base_pos=jnp.asarray(m.body_pos[base]),
            base_rot=jnp.asarray(rot.reshape(3, 3)),
            shoulder_height=jnp.asarray(shoulder),
            upper_arm=jnp.asarray(m.body_pos[body("forearm")][2]),
            forearm=jnp.asarray(forearm),
            q_lo=jnp.asarray(rng[:, 0]),
            q_hi=jnp.asarray(rng[:, 1]),
        )


def rot_x(a: jax.Array) -> jax.Array:
    c, s = jnp.cos(a), jnp.sin(a)
    one, zero = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.array([[one, zero, zero], [zero, c, -s], [zero, s, c]])


def rot_y(a: jax.Array) -> jax.Array:
    c, s = jnp.cos(a), jnp.sin(a)
    one, zero = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.array([[c, zero, s], [zero, one, zero], [-s, zero, c]])


def rot_z(a: jax.Array) -> jax.Array:
    c, s = jnp.cos(a), jnp.sin(a)
    one, zero = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.array([[c, -s, zero], [s, c, zero], [zero, zero, one]])


def axis_angle(rotvec: jax.Array) -> jax.Array:
    """Rotation matrix of a rotation vector (Rodrigues), exact at zero."""
    theta = jnp.linalg.norm(rotvec)
    safe = jnp.where(theta > 1e-12, theta, 1.0)
    k = rotvec / safe
    kx = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    r = jnp.eye(3) + jnp.sin(theta) * kx + (1.0 - jnp.cos(theta)) * kx @ kx
    return jnp.where(theta > 1e-12, r, jnp.eye(3))


def fk(g: ArmGeometry, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World position of the wrist centre and world rotation of the gripper frame."""
    r_shoulder = g.base_rot @ rot_z(q[0])
    upper = r_shoulder @ rot_y(q[1]) @ jnp.array([0.0, 0.0, 1.0]) * g.upper_arm
    r_forearm = r_shoulder @ rot_y(q[1] + q[2])
    wrist = (
        g.base_pos
        + g.base_rot @ jnp.array([0.0, 0.0, 1.0]) * g.shoulder_height
        + upper
        + r_forearm[:, 0] * g.forearm
    )
    rot = r_forearm @ rot_x(q[3]) @ rot_y(q[4]) @ rot_x(q[5])
    return wrist, rot


def gripper_points(
    g: ArmGeometry, q: jax.Array, fingers: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(ee position, gripper rotation, GC) for joint angles q and finger openings."""
    wrist, rot = fk(g, q)
    ee = wrist + rot[:, 0] * rc.EE_SITE_X
    gc_local = jnp.array([rc.PAD_X, 0.5 * (fingers[0] - fingers[1]), 0.0])
    return ee, rot, wrist + rot @ gc_local


def _wrap_near(a: jax.Array, ref: jax.Array) -> jax.Array:
    """The angle equal to a modulo 2 pi that is closest to ref."""
    return ref + jnp.mod(a - ref + jnp.pi, _TWO_PI) - jnp.pi


def _principal(a: jax.Array) -> jax.Array:
    return jnp.mod(a + jnp.pi, _TWO_PI) - jnp.pi


def _in_limits(q: jax.Array, lo: jax.Array, hi: jax.Array) -> jax.Array:
    return jnp.all((q >= lo - _LIMIT_TOL) & (q <= hi + _LIMIT_TOL))


def _near_within(a: jax.Array, ref: jax.Array, lo: jax.Array, hi: jax.Array) -> jax.Array:
    """a modulo 2 pi: the copy nearest ref if it is within limits, else the principal one."""
    near = _wrap_near(a, ref)
    return jnp.where((near >= lo) & (near <= hi), near, _principal(a))


def ik(
    g: ArmGeometry, ee: jax.Array, rot: jax.Array, q_prev: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Joint angles placing the ee site at `ee` with gripper rotation `rot`.

    Of the solutions (elbow up only; two wrist branches, each modulo 2 pi) it returns the one
    nearest to q_prev, so that a path of nearby poses gives a continuous joint path.
    Returns (q, ok): ok is false when the pose is out of reach or every solution violates a
    joint limit; q is then meaningless.
    """
    p = g.base_rot.T @ (ee - g.base_pos)
    r_local = g.base_rot.T @ rot
    w = p - r_local[:, 0] * rc.EE_SITE_X
    l1, l2 = g.upper_arm, g.forearm

    q0 = _near_within(jnp.arctan2(w[1], w[0]), q_prev[0], g.q_lo[0], g.q_hi[0])
    radial = jnp.hypot(w[0], w[1])
    height = w[2] - g.shoulder_height
    sin_q2 = (l1 * l1 + l2 * l2 - radial * radial - height * height) / (2.0 * l1 * l2)
    reach_ok = jnp.abs(sin_q2) <= 1.0 - 1e-6
    q2 = jnp.arcsin(jnp.clip(sin_q2, -1.0, 1.0))
    q1 = jnp.arctan2(radial, height) - jnp.arctan2(l2 * jnp.cos(q2), l1 - l2 * jnp.sin(q2))
    # atan2(w_y, w_x) puts the wrist in front of the waist (radial >= 0); when the wrist is on
    # the waist axis the waist angle is free and the previous value is kept.
    q0 = jnp.where(radial > 1e-9, q0, q_prev[0])

    m = (rot_z(q0) @ rot_y(q1 + q2)).T @ r_local  # = rot_x(q3) rot_y(q4) rot_x(q5)
    sin_b = jnp.hypot(m[1, 0], m[2, 0])
    b = jnp.arctan2(sin_b, m[0, 0])
    a = jnp.arctan2(m[1, 0], -m[2, 0])
    c = jnp.arctan2(m[0, 1], m[0, 2])
    # Near b = 0 the two rolls are one rotation; keep the forearm roll where it was.
    singular = sin_b < 1e-7
    a = jnp.where(singular, q_prev[3], a)
    c = jnp.where(singular, jnp.arctan2(m[2, 1], m[1, 1]) - q_prev[3], c)

    def candidate(a_: jax.Array, b_: jax.Array, c_: jax.Array) -> jax.Array:
        return jnp.stack(
            [
                q0,
                q1,
                q2,
                _near_within(a_, q_prev[3], g.q_lo[3], g.q_hi[3]),
                b_,
                _near_within(c_, q_prev[5], g.q_lo[5], g.q_hi[5]),
            ]
        )

    first = candidate(a, b, c)
    second = candidate(a + jnp.pi, -b, c + jnp.pi)
    ok1 = _in_limits(first, g.q_lo, g.q_hi)
    ok2 = _in_limits(second, g.q_lo, g.q_hi)
    d1 = jnp.sum(jnp.square(first - q_prev))
    d2 = jnp.sum(jnp.square(second - q_prev))
    take_second = ok2 & (~ok1 | (d2 < d1))
    q = jnp.where(take_second, second, first)
    return q, reach_ok & (ok1 | ok2)


def gripper_box_corners(fingers: jax.Array) -> jax.Array:
    """Corners (24, 3) of the palm and finger collision boxes in the gripper frame."""
    signs = jnp.array(
        [[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0) for sz in (-1.0, 1.0)]
    )
    out = []
    for (centre, half), shift in (
        (rc.PALM_BOX, 0.0),
        (rc.FINGER_A_BOX, fingers[0]),
        (rc.FINGER_B_BOX, -fingers[1]),
    ):
        c = jnp.asarray(centre) + jnp.array([0.0, 1.0, 0.0]) * shift
        out.append(c + signs * jnp.asarray(half))
    return jnp.concatenate(out)


def lowest_gripper_z(g: ArmGeometry, q: jax.Array, fingers: jax.Array) -> jax.Array:
    """World height of the lowest corner of the gripper's collision boxes."""
    wrist, rot = fk(g, q)
    corners = wrist + gripper_box_corners(fingers) @ rot.T
    return jnp.min(corners[:, 2])


def mat_to_quat(r: jax.Array) -> jax.Array:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method)."""
    tr = jnp.trace(r)
    cands = jnp.stack(
        [
            jnp.array([1.0 + tr, r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]),
            jnp.array(
                [r[2, 1] - r[1, 2], 1.0 + 2 * r[0, 0] - tr, r[0, 1] + r[1, 0], r[0, 2] + r[2, 0]]
            ),
            jnp.array(
                [r[0, 2] - r[2, 0], r[0, 1] + r[1, 0], 1.0 + 2 * r[1, 1] - tr, r[1, 2] + r[2, 1]]
            ),
            jnp.array(
                [r[1, 0] - r[0, 1], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], 1.0 + 2 * r[2, 2] - tr]
            ),
        ]
    )
    i = jnp.argmax(jnp.array([tr, r[0, 0], r[1, 1], r[2, 2]]))
    quat = cands[i]
    quat = quat / jnp.linalg.norm(quat)
    return jnp.where(quat[0] < 0, -quat, quat)


def mat_to_rpy(r: jax.Array) -> jax.Array:
    """Roll, pitch, yaw (rad) with r = Rz(yaw) Ry(pitch) Rx(roll)."""
    roll = jnp.arctan2(r[2, 1], r[2, 2])
    pitch = jnp.arcsin(jnp.clip(-r[2, 0], -1.0, 1.0))
    yaw = jnp.arctan2(r[1, 0], r[0, 0])
    return jnp.stack([roll, pitch, yaw])
