"""The closed-form kinematics of `kinematics.py` as Warp functions, for the Warp backend's kernels.

Forward kinematics, gripper points, the IK with its branch choice, the gripper's lowest point
and the rotation conversions: the formulas, branch choices and tolerances of the JAX originals,
line for line (tests/test_warp_control.py holds the port to them). The kernels that call these
live in `control.py` (the plan and the joint references) and `arm_indices.py` (the
proprioception).

Conventions as in `kinematics.py`: joint vectors are `vec6`, the gripper rotation has columns
(rx, ry, rz) = approach, finger-closing and palm-side axes in the world frame.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from vabench.sim_mjx import kinematics as kin
from vabench.sim_mjx import robot_constants as rc

vec6 = wp.types.vector(length=6, dtype=wp.float32)

_PI = wp.constant(math.pi)
_TWO_PI = wp.constant(2.0 * math.pi)
_LIMIT_TOL = wp.constant(1e-6)
_EE_SITE_X = wp.constant(rc.EE_SITE_X)
_PAD_X = wp.constant(rc.PAD_X)

# Gripper collision boxes (centre, half size) in the gripper frame; fingers at zero opening.
_PALM_C = wp.constant(wp.vec3(*rc.PALM_BOX[0]))
_PALM_H = wp.constant(wp.vec3(*rc.PALM_BOX[1]))
_FA_C = wp.constant(wp.vec3(*rc.FINGER_A_BOX[0]))
_FA_H = wp.constant(wp.vec3(*rc.FINGER_A_BOX[1]))
_FB_C = wp.constant(wp.vec3(*rc.FINGER_B_BOX[0]))
_FB_H = wp.constant(wp.vec3(*rc.FINGER_B_BOX[1]))


@wp.struct
class ArmGeometryW:
    """`kinematics.ArmGeometry` of one arm."""

    base_pos: wp.vec3
    base_rot: wp.mat33
    shoulder_height: float
    upper_arm: float
    forearm: float
    q_lo: vec6
    q_hi: vec6


def arm_geometries(geoms: kin.ArmGeometry, device: wp.context.Device | str) -> wp.array:
    """The JAX geometry stacked over arms (leading axis A) as a Warp array of structs (A,)."""
    g = {k: np.asarray(v) for k, v in vars(geoms).items()}
    out = []
    for a in range(len(g["base_pos"])):
        s = ArmGeometryW()
        s.base_pos = wp.vec3(*g["base_pos"][a].tolist())
        s.base_rot = wp.mat33(*g["base_rot"][a].reshape(-1).tolist())
        s.shoulder_height = float(g["shoulder_height"][a])
        s.upper_arm = float(g["upper_arm"][a])
        s.forearm = float(g["forearm"][a])
        s.q_lo = vec6(*g["q_lo"][a].tolist())
        s.q_hi = vec6(*g["q_hi"][a].tolist())
        out.append(s)
    return wp.array(out, dtype=ArmGeometryW, device=device)


@wp.func
def rot_x(a: float) -> wp.mat33:
    c, s = wp.cos(a), wp.sin(a)
    return wp.mat33(1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c)


@wp.func
def rot_y(a: float) -> wp.mat33:
    c, s = wp.cos(a), wp.sin(a)
    return wp.mat33(c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c)


@wp.func
def rot_z(a: float) -> wp.mat33:
    c, s = wp.cos(a), wp.sin(a)
    return wp.mat33(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)


@wp.func
def column(m: wp.mat33, j: int) -> wp.vec3:
    return wp.vec3(m[0, j], m[1, j], m[2, j])


@wp.func
def axis_angle(rotvec: wp.vec3) -> wp.mat33:
    """Rotation matrix of a rotation vector (Rodrigues), exact at zero."""
    theta = wp.length(rotvec)
    if theta <= 1.0e-12:
        return wp.identity(n=3, dtype=float)
    k = rotvec / theta
    kx = wp.mat33(0.0, -k[2], k[1], k[2], 0.0, -k[0], -k[1], k[0], 0.0)
    return wp.identity(n=3, dtype=float) + wp.sin(theta) * kx + (1.0 - wp.cos(theta)) * (kx @ kx)


@wp.func
def fk(g: ArmGeometryW, q: vec6):
    """World position of the wrist centre and world rotation of the gripper frame."""
    r_shoulder = g.base_rot @ rot_z(q[0])
    upper = column(r_shoulder @ rot_y(q[1]), 2) * g.upper_arm
    r_forearm = r_shoulder @ rot_y(q[1] + q[2])
    wrist = (
        g.base_pos
        + column(g.base_rot, 2) * g.shoulder_height
        + upper
        + column(r_forearm, 0) * g.forearm
    )
    rot = r_forearm @ rot_x(q[3]) @ rot_y(q[4]) @ rot_x(q[5])
    return wrist, rot


@wp.func
def gripper_points(g: ArmGeometryW, q: vec6, fingers: wp.vec2):
    """(ee position, gripper rotation, GC) for joint angles q and finger openings."""
    wrist, rot = fk(g, q)
    ee = wrist + column(rot, 0) * _EE_SITE_X
    gc_local = wp.vec3(_PAD_X, 0.5 * (fingers[0] - fingers[1]), 0.0)
    return ee, rot, wrist + rot @ gc_local


@wp.func
def floor_mod(x: float, y: float) -> float:
    """x mod y with the sign of y, as jnp.mod (wp.mod is C's fmod)."""
    r = wp.mod(x, y)
    if r != 0.0 and (r < 0.0) != (y < 0.0):
        r = r + y
    return r


@wp.func
def wrap_near(a: float, ref: float) -> float:
    return ref + floor_mod(a - ref + _PI, _TWO_PI) - _PI


@wp.func
def principal(a: float) -> float:
    return floor_mod(a + _PI, _TWO_PI) - _PI


@wp.func
def near_within(a: float, ref: float, lo: float, hi: float) -> float:
    """a modulo 2 pi: the copy nearest ref if it is within limits, else the principal one."""
    near = wrap_near(a, ref)
    return wp.where((near >= lo) and (near <= hi), near, principal(a))


@wp.func
def in_limits(q: vec6, lo: vec6, hi: vec6) -> bool:
    ok = wp.bool(True)  # a variable, not a constant: it changes in the loop
    for j in range(6):
        ok = ok and (q[j] >= lo[j] - _LIMIT_TOL) and (q[j] <= hi[j] + _LIMIT_TOL)
    return ok


@wp.func
def ik(g: ArmGeometryW, ee: wp.vec3, rot: wp.mat33, q_prev: vec6):
    """Joint angles placing the ee site at `ee` with gripper rotation `rot`: of the solutions
    (elbow up; two wrist branches, each modulo 2 pi) the one nearest q_prev; and whether the
    pose is reachable within the joint limits (see kinematics.ik)."""
    base_t = wp.transpose(g.base_rot)
    p = base_t @ (ee - g.base_pos)
    r_local = base_t @ rot
    w = p - column(r_local, 0) * _EE_SITE_X
    l1, l2 = g.upper_arm, g.forearm

    q0 = near_within(wp.atan2(w[1], w[0]), q_prev[0], g.q_lo[0], g.q_hi[0])
    radial = wp.sqrt(w[0] * w[0] + w[1] * w[1])
    height = w[2] - g.shoulder_height
    sin_q2 = (l1 * l1 + l2 * l2 - radial * radial - height * height) / (2.0 * l1 * l2)
    reach_ok = wp.abs(sin_q2) <= 1.0 - 1.0e-6
    q2 = wp.asin(wp.clamp(sin_q2, -1.0, 1.0))
    q1 = wp.atan2(radial, height) - wp.atan2(l2 * wp.cos(q2), l1 - l2 * wp.sin(q2))
    # On the waist axis the waist angle is free: keep the previous one.
    q0 = wp.where(radial > 1.0e-9, q0, q_prev[0])

    m = wp.transpose(rot_z(q0) @ rot_y(q1 + q2)) @ r_local  # = rot_x(q3) rot_y(q4) rot_x(q5)
    sin_b = wp.sqrt(m[1, 0] * m[1, 0] + m[2, 0] * m[2, 0])
    b = wp.atan2(sin_b, m[0, 0])
    a = wp.atan2(m[1, 0], -m[2, 0])
    c = wp.atan2(m[0, 1], m[0, 2])
    # Near b = 0 the two rolls are one rotation; keep the forearm roll where it was.
    if sin_b < 1.0e-7:
        a = q_prev[3]
        c = wp.atan2(m[2, 1], m[1, 1]) - q_prev[3]

    first = vec6(
        q0,
        q1,
        q2,
        near_within(a, q_prev[3], g.q_lo[3], g.q_hi[3]),
        b,
        near_within(c, q_prev[5], g.q_lo[5], g.q_hi[5]),
    )
    second = vec6(
        q0,
        q1,
        q2,
        near_within(a + _PI, q_prev[3], g.q_lo[3], g.q_hi[3]),
        -b,
        near_within(c + _PI, q_prev[5], g.q_lo[5], g.q_hi[5]),
    )
    ok1 = in_limits(first, g.q_lo, g.q_hi)
    ok2 = in_limits(second, g.q_lo, g.q_hi)
    d1 = wp.dot(first - q_prev, first - q_prev)
    d2 = wp.dot(second - q_prev, second - q_prev)
    take_second = ok2 and ((not ok1) or (d2 < d1))
    q = wp.where(take_second, second, first)
    return q, reach_ok and (ok1 or ok2)


@wp.func
def box_low(wrist: wp.vec3, rot: wp.mat33, centre: wp.vec3, half: wp.vec3) -> float:
    """World height of the lowest corner of a box given in the gripper frame."""
    low = wp.float32(1.0e30)
    for i in range(8):
        sx = wp.where((i & 4) != 0, 1.0, -1.0)
        sy = wp.where((i & 2) != 0, 1.0, -1.0)
        sz = wp.where((i & 1) != 0, 1.0, -1.0)
        corner = centre + wp.vec3(sx * half[0], sy * half[1], sz * half[2])
        low = wp.min(low, wrist[2] + wp.dot(wp.vec3(rot[2, 0], rot[2, 1], rot[2, 2]), corner))
    return low


@wp.func
def lowest_gripper_z(g: ArmGeometryW, q: vec6, fingers: wp.vec2) -> float:
    """World height of the lowest corner of the gripper's collision boxes."""
    wrist, rot = fk(g, q)
    low = box_low(wrist, rot, _PALM_C, _PALM_H)
    low = wp.min(low, box_low(wrist, rot, _FA_C + wp.vec3(0.0, fingers[0], 0.0), _FA_H))
    return wp.min(low, box_low(wrist, rot, _FB_C - wp.vec3(0.0, fingers[1], 0.0), _FB_H))


@wp.func
def mat_to_quat(r: wp.mat33) -> wp.vec4:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method)."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    best = tr
    i = wp.int32(0)
    if r[0, 0] > best:
        best = r[0, 0]
        i = 1
    if r[1, 1] > best:
        best = r[1, 1]
        i = 2
    if r[2, 2] > best:
        i = 3
    q = wp.vec4(1.0 + tr, r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1])
    if i == 1:
        q = wp.vec4(
            r[2, 1] - r[1, 2], 1.0 + 2.0 * r[0, 0] - tr, r[0, 1] + r[1, 0], r[0, 2] + r[2, 0]
        )
    elif i == 2:
        q = wp.vec4(
            r[0, 2] - r[2, 0], r[0, 1] + r[1, 0], 1.0 + 2.0 * r[1, 1] - tr, r[1, 2] + r[2, 1]
        )
    elif i == 3:
        q = wp.vec4(
            r[1, 0] - r[0, 1], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], 1.0 + 2.0 * r[2, 2] - tr
        )
    q = q / wp.length(q)
    return wp.where(q[0] < 0.0, -q, q)


@wp.func
def mat_to_rpy(r: wp.mat33) -> wp.vec3:
    """Roll, pitch, yaw (rad) with r = Rz(yaw) Ry(pitch) Rx(roll)."""
    return wp.vec3(
        wp.atan2(r[2, 1], r[2, 2]),
        wp.asin(wp.clamp(-r[2, 0], -1.0, 1.0)),
        wp.atan2(r[1, 0], r[0, 0]),
    )
