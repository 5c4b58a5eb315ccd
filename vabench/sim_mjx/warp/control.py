"""The fixed executor (`controller.py`) ported to Warp kernels: the plan and the joint references.

The port exists so that one CUDA graph per agent action holds everything the Warp backend
does for that action: the plan of every slot (`plan_kernel`: closed-form IK at each waypoint
with the reach, limit, wrist-flip and table checks), the joint references of every physics
substep (`ctrl_kernel`), and the proprioception after it (`arm_indices.proprio_kernel`), all on
device arrays with no host round trip. The formulas, branch choices and tolerances are those of
the JAX originals (which the C and MJX-JAX backends use), line for line; the kinematics they
call are in `fk_ik.py`; tests/test_warp_control.py holds the port to them.

Arrays are indexed [slot, arm] (and [slot, arm, waypoint] for the waypoints).
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx.warp.arm_indices import Indices, arm_q, pair
from vabench.sim_mjx.warp.fk_ik import (
    ArmGeometryW,
    axis_angle,
    gripper_points,
    ik,
    lowest_gripper_z,
    vec6,
)

W = rc.N_WAYPOINTS
_TABLE_LIMIT = wp.constant(rc.TABLE_Z + rc.TABLE_CLEARANCE)
_MAX_JOINT_STEP = wp.constant(rc.MAX_JOINT_STEP)
_N_WAYPOINTS = wp.constant(W)
_EE_LO = wp.constant(wp.vec3(*rc.EE_BOUNDS_LO))
_EE_HI = wp.constant(wp.vec3(*rc.EE_BOUNDS_HI))
_TURN_STEP = wp.constant(rc.ROTATION_WAYPOINT_RAD)
_TURN_CHECKS = wp.constant(rc.MAX_ROTATION_WAYPOINTS)
_TURN_SLACK = wp.constant(rc.ROTATION_WAYPOINT_SLACK)
_FINGER_OPEN = wp.constant(rc.FINGER_OPEN)
_FINGER_CLOSED = wp.constant(rc.FINGER_CLOSED)
_PACE_MOVE = wp.constant(rc.PACE_FULL_MOVE_M)
_PACE_TURN = wp.constant(rc.PACE_FULL_TURN_RAD)
_PACE_MIN = wp.constant(rc.PACE_MIN)


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
    move_steps: wp.array  # (N, A) float
    grip_steps: wp.array  # (N, A) float
    rest_from: wp.array  # (N,) int

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
            move_steps=z(float),
            grip_steps=z(float),
            rest_from=z(int, n),
        )


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
    turns = (rotvec[0] != 0.0) or (rotvec[1] != 0.0) or (rotvec[2] != 0.0)
    ee_clipped = wp.vec3(
        wp.clamp(ee_end[0], _EE_LO[0], _EE_HI[0]),
        wp.clamp(ee_end[1], _EE_LO[1], _EE_HI[1]),
        wp.clamp(ee_end[2], _EE_LO[2], _EE_HI[2]),
    )
    if turns:  # a rotation is never clipped: refused whole when a waypoint leaves the bounds
        ee_clipped = ee_end
    shift = ee_clipped - ee_end
    turn_ok = wp.bool(True)
    if turns:
        n_turn = wp.max(wp.ceil(wp.length(rotvec) / _TURN_STEP - _TURN_SLACK), 1.0)
        for k in range(_TURN_CHECKS):
            tk = wp.min(float(k + 1) / n_turn, 1.0)
            ee_k = gc - (rot @ axis_angle(tk * rotvec)) @ gc_local
            for j in range(3):
                if ee_k[j] < _EE_LO[j] - 1.0e-9 or ee_k[j] > _EE_HI[j] + 1.0e-9:
                    turn_ok = False
    clipped = (wp.abs(shift[0]) > 1.0e-9) or (wp.abs(shift[1]) > 1.0e-9)
    clipped = clipped or (wp.abs(shift[2]) > 1.0e-9)
    moves = (delta[0] != 0.0) or (delta[1] != 0.0) or (delta[2] != 0.0)
    moves = moves or (rotvec[0] != 0.0) or (rotvec[1] != 0.0) or (rotvec[2] != 0.0)

    ok = turn_ok
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


@wp.kernel
def pace_kernel(
    paced: int,
    full_move: float,
    full_grip: float,
    fixed_rest: int,
    executed_m: wp.array2d(dtype=float),
    cmd_rotvec: wp.array2d(dtype=wp.vec3),
    moves: wp.array2d(dtype=int),
    finger_start: wp.array2d(dtype=wp.vec2),
    finger_target: wp.array2d(dtype=wp.vec2),
    move_steps: wp.array2d(dtype=float),
    grip_steps: wp.array2d(dtype=float),
    rest_from: wp.array(dtype=int),
):
    """The timing of slot n's action (controller.pace): fixed, or paced by each move's length."""
    n = wp.tid()
    final = full_move * 0.0  # a variable (not a constant) the loop may raise
    for a in range(moves.shape[1]):
        steps = full_move
        if paced != 0:
            length = wp.max(executed_m[n, a] / _PACE_MOVE, wp.length(cmd_rotvec[n, a]) / _PACE_TURN)
            steps = full_move * wp.clamp(wp.sqrt(length), _PACE_MIN, 1.0)
            if moves[n, a] != 0:
                final = wp.max(final, steps)
            f0, f1 = finger_start[n, a], finger_target[n, a]
            if f0[0] != f1[0] or f0[1] != f1[1]:
                final = wp.max(final, full_grip)
        move_steps[n, a] = steps
        grip_steps[n, a] = full_grip
    rest_from[n] = fixed_rest
    if paced != 0:
        rest_from[n] = wp.max(int(wp.ceil(final)), 1)


@wp.func
def min_jerk(s: float) -> float:
    s = wp.clamp(s, 0.0, 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


@wp.kernel
def ctrl_kernel(
    step: wp.array(dtype=int),
    move_steps: wp.array2d(dtype=float),
    grip_steps: wp.array2d(dtype=float),
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
    u = min_jerk(kk / move_steps[n, a]) * float(_N_WAYPOINTS - 1)
    i = wp.clamp(int(wp.floor(u)), 0, _N_WAYPOINTS - 2)
    frac = u - float(i)
    w0 = waypoints[n, a, i]
    arm = w0 + frac * (waypoints[n, a, i + 1] - w0)
    if moves[n, a] == 0:
        arm = hold[n, a]
    s = wp.clamp(kk / grip_steps[n, a], 0.0, 1.0)
    f0 = finger_start[n, a]
    fingers = f0 + s * (finger_target[n, a] - f0)
    for j in range(6):
        ctrl[n, arm_act[a, j]] = arm[j]
    ctrl[n, finger_act[a, 0]] = fingers[0]
    ctrl[n, finger_act[a, 1]] = fingers[1]


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
    n_substeps: int,
    fixed_rest: int,
    paced: bool = False,
) -> None:
    """Plan every slot's command over `n_substeps`, its timing fixed (final after
    `fixed_rest`) or `paced`; ok / go per slot (see slot_ok_kernel)."""
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
    wp.launch(
        pace_kernel,
        dim=n,
        inputs=[
            int(paced),
            float(rc.MOVE_FRACTION * n_substeps),
            float(rc.GRIP_FRACTION * n_substeps),
            fixed_rest,
            plan.executed_m,
            rotvec,
            plan.moves,
            plan.finger_start,
            plan.finger_target,
        ],
        outputs=[plan.move_steps, plan.grip_steps, plan.rest_from],
    )


def launch_ctrl(step: wp.array, plan: PlanBuffers, idx: Indices, ctrl: wp.array) -> None:
    """Write the references of substep step[0] (a device counter) into ctrl."""
    wp.launch(
        ctrl_kernel,
        dim=plan.moves.shape,
        inputs=[
            step,
            plan.move_steps,
            plan.grip_steps,
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
