"""The fixed executor (`kinematics.py`, `controller.py`) ported to Warp kernels.

The port exists so that one CUDA graph per agent action holds everything the Warp backend
does for that action: the plan of every slot (closed-form IK at each waypoint with the
reach, limit, wrist-flip and table checks), the joint references of every physics substep, and
the proprioception after it, all on device arrays with no host round trip. The formulas, branch
choices and tolerances are those of the JAX originals (which the C and MJX-JAX backends use),
line for line; tests/test_warp_control.py holds the port to them.

Conventions as in `kinematics.py`: joint vectors are `vec6`, the gripper rotation has columns
(rx, ry, rz) = approach, finger-closing and palm-side axes in the world frame. Arrays are
indexed [slot, arm] (and [slot, arm, waypoint] for the waypoints).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from vabench.sim_mjx import kinematics as kin
from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx.layout import ArmLayout

vec6 = wp.types.vector(length=6, dtype=wp.float32)

W = rc.N_WAYPOINTS
_PI = wp.constant(math.pi)
_TWO_PI = wp.constant(2.0 * math.pi)
_LIMIT_TOL = wp.constant(1e-6)
_EE_SITE_X = wp.constant(rc.EE_SITE_X)
_PAD_X = wp.constant(rc.PAD_X)
_TABLE_LIMIT = wp.constant(rc.TABLE_Z + rc.TABLE_CLEARANCE)
_MAX_JOINT_STEP = wp.constant(rc.MAX_JOINT_STEP)
_N_WAYPOINTS = wp.constant(W)
_EE_LO = wp.constant(wp.vec3(*rc.EE_BOUNDS_LO))
_EE_HI = wp.constant(wp.vec3(*rc.EE_BOUNDS_HI))
_FINGER_OPEN = wp.constant(rc.FINGER_OPEN)
_FINGER_CLOSED = wp.constant(rc.FINGER_CLOSED)
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


@dataclass
class Indices:
    """`ArmLayout` addresses as device arrays: (A, 6) and (A, 2) qpos addresses and ids."""

    arm_qadr: wp.array
    finger_qadr: wp.array
    arm_act: wp.array
    finger_act: wp.array


def layout_arrays(layout: ArmLayout, device: wp.context.Device | str) -> Indices:
    def arr(x: np.ndarray) -> wp.array:
        return wp.array(np.asarray(x, np.int32), dtype=int, device=device)

    return Indices(
        arr(layout.qpos), arr(layout.fingers), arr(layout.arm_act), arr(layout.finger_act)
    )


@dataclass
class PlanBuffers:
    """Per slot and arm: the plan of `controller.Plan`."""

    waypoints: wp.array  # (N, A, W) vec6
    hold: wp.array  # (N, A) vec6: the arm reference held before the action
    moves: wp.array  # (N, A) int
    finger_start: wp.array  # (N, A) vec2
    finger_target: wp.array  # (N, A) vec2
    arm_ok: wp.array  # (N, A) int
    clipped: wp.array  # (N, A) int
    executed_m: wp.array  # (N, A) float

    @staticmethod
    def allocate(n: int, n_arms: int, device: wp.context.Device | str) -> PlanBuffers:
        def z(dtype: type, *shape: int) -> wp.array:
            return wp.zeros(shape or (n, n_arms), dtype=dtype, device=device)

        return PlanBuffers(
            waypoints=z(vec6, n, n_arms, W),
            hold=z(vec6),
            moves=z(int),
            finger_start=z(wp.vec2),
            finger_target=z(wp.vec2),
            arm_ok=z(int),
            clipped=z(int),
            executed_m=z(float),
        )


@dataclass
class ProprioBuffers:
    """Per slot and arm: the fields of `layout.Proprio` (grip state apart)."""

    gc: wp.array  # (N, A) vec3
    ee: wp.array  # (N, A) vec3
    rot: wp.array  # (N, A) mat33
    quat: wp.array  # (N, A) vec4, w x y z
    rpy: wp.array  # (N, A) vec3
    fingers: wp.array  # (N, A) vec2

    @staticmethod
    def allocate(n: int, n_arms: int, device: wp.context.Device | str) -> ProprioBuffers:
        def z(dtype: type) -> wp.array:
            return wp.zeros((n, n_arms), dtype=dtype, device=device)

        return ProprioBuffers(
            z(wp.vec3), z(wp.vec3), z(wp.mat33), z(wp.vec4), z(wp.vec3), z(wp.vec2)
        )


# -- kinematics -------------------------------------------------------------------------------
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


# -- planning ---------------------------------------------------------------------------------
@wp.func
def arm_q(qpos: wp.array2d(dtype=float), n: int, adr: wp.array2d(dtype=int), a: int) -> vec6:
    return vec6(
        qpos[n, adr[a, 0]],
        qpos[n, adr[a, 1]],
        qpos[n, adr[a, 2]],
        qpos[n, adr[a, 3]],
        qpos[n, adr[a, 4]],
        qpos[n, adr[a, 5]],
    )


@wp.func
def pair(x: wp.array2d(dtype=float), n: int, adr: wp.array2d(dtype=int), a: int) -> wp.vec2:
    return wp.vec2(x[n, adr[a, 0]], x[n, adr[a, 1]])


@wp.kernel
def plan_kernel(
    geoms: wp.array(dtype=ArmGeometryW),
    qpos: wp.array2d(dtype=float),
    ctrl: wp.array2d(dtype=float),
    arm_qadr: wp.array2d(dtype=int),
    finger_qadr: wp.array2d(dtype=int),
    arm_act: wp.array2d(dtype=int),
    finger_act: wp.array2d(dtype=int),
    cmd_delta: wp.array2d(dtype=wp.vec3),
    cmd_rotvec: wp.array2d(dtype=wp.vec3),
    cmd_grip: wp.array2d(dtype=int),
    waypoints: wp.array3d(dtype=vec6),
    hold: wp.array2d(dtype=vec6),
    moves_out: wp.array2d(dtype=int),
    finger_start: wp.array2d(dtype=wp.vec2),
    finger_target: wp.array2d(dtype=wp.vec2),
    arm_ok: wp.array2d(dtype=int),
    clipped_out: wp.array2d(dtype=int),
    executed_m: wp.array2d(dtype=float),
):
    """The plan of arm a of slot n (controller._plan_arm and plan_slot)."""
    n, a = wp.tid()
    g = geoms[a]
    q = arm_q(qpos, n, arm_qadr, a)
    fingers = pair(qpos, n, finger_qadr, a)
    delta = cmd_delta[n, a]
    rotvec = cmd_rotvec[n, a]

    ee, rot, gc = gripper_points(g, q, fingers)
    gc_local = wp.transpose(rot) @ (gc - ee)  # GC seen from the ee frame: fixed in a rotation
    rot_end = rot @ axis_angle(rotvec)
    ee_end = gc + delta - rot_end @ gc_local
    ee_clipped = wp.vec3(
        wp.clamp(ee_end[0], _EE_LO[0], _EE_HI[0]),
        wp.clamp(ee_end[1], _EE_LO[1], _EE_HI[1]),
        wp.clamp(ee_end[2], _EE_LO[2], _EE_HI[2]),
    )
    shift = ee_clipped - ee_end
    clipped = (wp.abs(shift[0]) > 1.0e-9) or (wp.abs(shift[1]) > 1.0e-9)
    clipped = clipped or (wp.abs(shift[2]) > 1.0e-9)
    moves = (delta[0] != 0.0) or (delta[1] != 0.0) or (delta[2] != 0.0)
    moves = moves or (rotvec[0] != 0.0) or (rotvec[1] != 0.0) or (rotvec[2] != 0.0)

    ok = wp.bool(True)
    q_prev = vec6(q)
    for i in range(_N_WAYPOINTS):
        t = float(i) / float(_N_WAYPOINTS - 1)
        r = rot @ axis_angle(t * rotvec)
        p = gc + t * (delta + shift) - r @ gc_local
        qi, reach = ik(g, p, r, q_prev)
        low = lowest_gripper_z(g, qi, fingers)
        step = qi - q_prev
        big = wp.float32(0.0)
        for j in range(6):
            big = wp.max(big, wp.abs(step[j]))
        ok = ok and reach and (big <= _MAX_JOINT_STEP) and (low >= _TABLE_LIMIT)
        waypoints[n, a, i] = wp.where(moves, qi, q)
        q_prev = qi

    hold[n, a] = arm_q(ctrl, n, arm_act, a)
    moves_out[n, a] = wp.where(moves, 1, 0)
    arm_ok[n, a] = wp.where(moves and not ok, 0, 1)
    clipped_out[n, a] = wp.where(clipped and moves, 1, 0)
    executed_m[n, a] = wp.where(moves, wp.length(delta + shift), 0.0)
    start = pair(ctrl, n, finger_act, a)
    grip = cmd_grip[n, a]
    target = start
    if grip == 1:
        target = wp.vec2(_FINGER_OPEN, _FINGER_OPEN)
    elif grip == 0:
        target = wp.vec2(_FINGER_CLOSED, _FINGER_CLOSED)
    finger_start[n, a] = start
    finger_target[n, a] = target


@wp.kernel
def slot_ok_kernel(
    arm_ok: wp.array2d(dtype=int),
    active: wp.array(dtype=int),
    ok: wp.array(dtype=int),
    go: wp.array(dtype=int),
):
    """ok[n]: every arm's plan succeeded; go[n]: the slot acts and its plan succeeded."""
    n = wp.tid()
    all_ok = wp.int32(1)
    for a in range(arm_ok.shape[1]):
        all_ok = all_ok * arm_ok[n, a]
    ok[n] = all_ok
    go[n] = wp.where(active[n] != 0 and all_ok != 0, 1, 0)


@wp.func
def min_jerk(s: float) -> float:
    s = wp.clamp(s, 0.0, 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


@wp.kernel
def ctrl_kernel(
    step: wp.array(dtype=int),
    move_steps: float,
    grip_steps: float,
    waypoints: wp.array3d(dtype=vec6),
    hold: wp.array2d(dtype=vec6),
    moves: wp.array2d(dtype=int),
    finger_start: wp.array2d(dtype=wp.vec2),
    finger_target: wp.array2d(dtype=wp.vec2),
    arm_act: wp.array2d(dtype=int),
    finger_act: wp.array2d(dtype=int),
    ctrl: wp.array2d(dtype=float),
):
    """Arm and finger references of substep k = step[0] (0-based) into ctrl
    (controller.ctrl_at). The substep comes from a device counter so that one recorded launch
    serves every substep of a graph's loop."""
    n, a = wp.tid()
    kk = float(step[0]) + 1.0
    u = min_jerk(kk / move_steps) * float(_N_WAYPOINTS - 1)
    i = wp.clamp(int(wp.floor(u)), 0, _N_WAYPOINTS - 2)
    frac = u - float(i)
    w0 = waypoints[n, a, i]
    arm = w0 + frac * (waypoints[n, a, i + 1] - w0)
    if moves[n, a] == 0:
        arm = hold[n, a]
    s = wp.clamp(kk / grip_steps, 0.0, 1.0)
    f0 = finger_start[n, a]
    fingers = f0 + s * (finger_target[n, a] - f0)
    for j in range(6):
        ctrl[n, arm_act[a, j]] = arm[j]
    ctrl[n, finger_act[a, 0]] = fingers[0]
    ctrl[n, finger_act[a, 1]] = fingers[1]


@wp.kernel
def proprio_kernel(
    geoms: wp.array(dtype=ArmGeometryW),
    qpos: wp.array2d(dtype=float),
    arm_qadr: wp.array2d(dtype=int),
    finger_qadr: wp.array2d(dtype=int),
    gc_out: wp.array2d(dtype=wp.vec3),
    ee_out: wp.array2d(dtype=wp.vec3),
    rot_out: wp.array2d(dtype=wp.mat33),
    quat_out: wp.array2d(dtype=wp.vec4),
    rpy_out: wp.array2d(dtype=wp.vec3),
    fingers_out: wp.array2d(dtype=wp.vec2),
):
    """Proprioception of arm a of slot n (layout.proprio_slot)."""
    n, a = wp.tid()
    fingers = pair(qpos, n, finger_qadr, a)
    ee, rot, gc = gripper_points(geoms[a], arm_q(qpos, n, arm_qadr, a), fingers)
    gc_out[n, a] = gc
    ee_out[n, a] = ee
    rot_out[n, a] = rot
    quat_out[n, a] = mat_to_quat(rot)
    rpy_out[n, a] = mat_to_rpy(rot)
    fingers_out[n, a] = fingers


# -- launches ---------------------------------------------------------------------------------
def launch_plan(
    geoms: wp.array,
    qpos: wp.array,
    ctrl: wp.array,
    idx: Indices,
    active: wp.array,
    delta: wp.array,
    rotvec: wp.array,
    grip: wp.array,
    plan: PlanBuffers,
    ok: wp.array,
    go: wp.array,
) -> None:
    """Plan every slot's command; ok / go per slot (see slot_ok_kernel)."""
    n, arms = delta.shape
    wp.launch(
        plan_kernel,
        dim=(n, arms),
        inputs=[geoms, qpos, ctrl, idx.arm_qadr, idx.finger_qadr, idx.arm_act, idx.finger_act]
        + [delta, rotvec, grip],
        outputs=[
            plan.waypoints,
            plan.hold,
            plan.moves,
            plan.finger_start,
            plan.finger_target,
            plan.arm_ok,
            plan.clipped,
            plan.executed_m,
        ],
    )
    wp.launch(slot_ok_kernel, dim=n, inputs=[plan.arm_ok, active], outputs=[ok, go])


def launch_ctrl(
    step: wp.array, n_substeps: int, plan: PlanBuffers, idx: Indices, ctrl: wp.array
) -> None:
    """Write the references of substep step[0] (a device counter) into ctrl."""
    wp.launch(
        ctrl_kernel,
        dim=plan.moves.shape,
        inputs=[
            step,
            float(rc.MOVE_FRACTION * n_substeps),
            float(rc.GRIP_FRACTION * n_substeps),
            plan.waypoints,
            plan.hold,
            plan.moves,
            plan.finger_start,
            plan.finger_target,
            idx.arm_act,
            idx.finger_act,
        ],
        outputs=[ctrl],
    )


def launch_proprio(
    geoms: wp.array, qpos: wp.array, idx: Indices, out: ProprioBuffers, grip_open: wp.array
) -> None:
    """Proprioception of every slot and arm into `out` (the grip state stays in grip_open)."""
    wp.launch(
        proprio_kernel,
        dim=grip_open.shape,
        inputs=[geoms, qpos, idx.arm_qadr, idx.finger_qadr],
        outputs=[out.gc, out.ee, out.rot, out.quat, out.rpy, out.fingers],
    )
