"""The fixed, model-agnostic executor: plan one metric action per slot, then a joint trajectory.

Every action, whatever its kind, is a per-arm command (`ArmCommand`): a world translation of the
end effector, a rotation vector about the current gripper-local axes (GC held fixed; a world
rotation arrives as the local one about the same axis, `actions.encode`), and an aperture
command. A slot's plan is
  1. the Cartesian target: translate, or rotate about GC (R' = R exp(rotvec), so the rotation is
     about the current local axis, right-handed); a translation's end-effector target is
     clipped to the workspace bounds of the reference and the clipping reported; a rotation
     is refused whole (planner failure, nothing moves) when the control point of any of its
     waypoints of at most 10 deg lies outside the bounds;
  2. N_WAYPOINTS poses along the straight line / the geodesic from the start, each solved in
     closed form (kinematics.ik) and checked: reachable, within joint limits, no wrist flip
     between neighbours, and every gripper collision box above the table;
  3. a joint reference over the action's physics substeps: minimum-jerk timing along the
     waypoints, held for the settle part; finger references ramp to open or closed. The
     timing is the same for every action, or paced by the move's length (`pace`).
If any commanded arm's plan fails, the slot's planner_success is false and the batch leaves the
slot untouched. The references are open-loop functions of time, so the same `ctrl_at` drives
MJX (inside a scan) and C MuJoCo (as a precomputed control sequence).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from vabench.sim_mjx import jax_setup  # noqa: F401  (JAX configured before it compiles)
from vabench.sim_mjx import kinematics as kin
from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx.pytree import PyTree, pytree_dataclass

GRIP_KEEP, GRIP_CLOSE, GRIP_OPEN = -1, 0, 1


@pytree_dataclass
class ArmCommand(PyTree):
    """One action for one slot (batched: a leading slot axis on every field)."""

    active: jax.Array  # () bool: the slot has an action this call
    delta: jax.Array  # (A, 3) world translation of the end effector, m
    rotvec: jax.Array  # (A, 3) rotation vector in the current gripper frame, rad
    grip: jax.Array  # (A,) int32: GRIP_KEEP, GRIP_CLOSE or GRIP_OPEN


@pytree_dataclass
class Plan(PyTree):
    waypoints: jax.Array  # (A, W, 6) joint waypoints (all equal to q when the arm stays)
    hold: jax.Array  # (A, 6) arm reference before the action (the previous control)
    moves: jax.Array  # (A,) bool: the arm follows its waypoints
    finger_start: jax.Array  # (A, 2)
    finger_target: jax.Array  # (A, 2)
    arm_ok: jax.Array  # (A,) bool
    ok: jax.Array  # () bool: every arm's plan succeeded
    clipped: jax.Array  # (A,) bool: the end-effector target was clipped to the bounds
    executed_m: jax.Array  # (A,) planned GC displacement after clipping, m
    move_steps: jax.Array  # (A,) substeps of the arm's minimum-jerk move
    grip_steps: jax.Array  # (A,) substeps of the fingers' ramp
    rest_from: jax.Array  # () int32: substeps after which every reference is final


def idle_command(n_arms: int) -> ArmCommand:
    return ArmCommand(
        active=jnp.array(False),
        delta=jnp.zeros((n_arms, 3)),
        rotvec=jnp.zeros((n_arms, 3)),
        grip=jnp.full((n_arms,), GRIP_KEEP, jnp.int32),
    )


def turn_waypoints(rotvec: jax.Array) -> jax.Array:
    """How many waypoints of at most ROTATION_WAYPOINT_RAD a rotation is checked at (>= 1)."""
    steps = jnp.linalg.norm(rotvec) / rc.ROTATION_WAYPOINT_RAD
    return jnp.maximum(jnp.ceil(steps - rc.ROTATION_WAYPOINT_SLACK), 1.0)


def _plan_arm(
    g: kin.ArmGeometry,
    q: jax.Array,
    fingers: jax.Array,
    delta: jax.Array,
    rotvec: jax.Array,
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array, jax.Array]:
    ee, rot, gc = kin.gripper_points(g, q, fingers)
    gc_local = rot.T @ (gc - ee)  # GC seen from the ee frame: fixed during a rotation
    rot_end = rot @ kin.axis_angle(rotvec)
    ee_end = gc + delta - rot_end @ gc_local
    lo, hi = jnp.asarray(rc.EE_BOUNDS_LO), jnp.asarray(rc.EE_BOUNDS_HI)
    turns = jnp.any(rotvec != 0.0)
    # A translation's target is clipped to the bounds; a rotation is never clipped (that would
    # move GC): it is refused whole when any of its waypoints of at most ROTATION_WAYPOINT_RAD
    # takes the control point outside them (the reference's rule).
    ee_clipped = jnp.where(turns, ee_end, jnp.clip(ee_end, lo, hi))
    shift = ee_clipped - ee_end
    clipped = jnp.any(jnp.abs(shift) > 1e-9)
    n_turn = turn_waypoints(rotvec)

    def turn_inside(k: jax.Array) -> jax.Array:
        ee_k = gc - rot @ kin.axis_angle(jnp.minimum(k / n_turn, 1.0) * rotvec) @ gc_local
        return jnp.all((ee_k >= lo - 1e-9) & (ee_k <= hi + 1e-9))

    turn_ok = jnp.all(jax.vmap(turn_inside)(jnp.arange(1.0, rc.MAX_ROTATION_WAYPOINTS + 1.0)))

    t = jnp.linspace(0.0, 1.0, rc.N_WAYPOINTS)

    def pose(ti: jax.Array) -> tuple[jax.Array, jax.Array]:
        r = rot @ kin.axis_angle(ti * rotvec)
        return gc + ti * (delta + shift) - r @ gc_local, r

    def solve(q_prev: jax.Array, ti: jax.Array) -> tuple[jax.Array, tuple[jax.Array, ...]]:
        p, r = pose(ti)
        qi, ok = kin.ik(g, p, r, q_prev)
        low = kin.lowest_gripper_z(g, qi, fingers)
        step_ok = jnp.max(jnp.abs(qi - q_prev)) <= rc.MAX_JOINT_STEP
        return qi, (qi, ok & step_ok & (low >= rc.TABLE_Z + rc.TABLE_CLEARANCE))

    _, (wps, oks) = jax.lax.scan(solve, q, t)
    moves = jnp.any(delta != 0.0) | jnp.any(rotvec != 0.0)
    ok = jnp.all(oks) & (turn_ok | ~turns)
    wps = jnp.where(moves, wps, jnp.broadcast_to(q, wps.shape))
    executed = jnp.linalg.norm(delta + shift)
    return wps, jnp.where(moves, ok, True), moves, clipped & moves, jnp.where(moves, executed, 0.0)


def pace(
    n_substeps: int,
    paced: bool,
    executed_m: jax.Array,
    rotvec: jax.Array,
    moves: jax.Array,
    finger_start: jax.Array,
    finger_target: jax.Array,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(move_steps (A,), grip_steps (A,), rest_from ()) of one slot's action. Fixed timing
    (`paced` false): every move MOVE_FRACTION and every ramp GRIP_FRACTION of the substeps, final
    after `rest_from(n_substeps)`. Paced: a move's time follows its length (robot_constants,
    PACE_*), final once the slowest moving part is (1 substep at least)."""
    full_move = jnp.float32(rc.MOVE_FRACTION * n_substeps)
    full_grip = jnp.float32(rc.GRIP_FRACTION * n_substeps)
    grip_steps = jnp.full(moves.shape, full_grip)
    if not paced:
        return jnp.full(moves.shape, full_move), grip_steps, jnp.int32(rest_from(n_substeps))
    length = jnp.maximum(
        executed_m / rc.PACE_FULL_MOVE_M, jnp.linalg.norm(rotvec, axis=-1) / rc.PACE_FULL_TURN_RAD
    )
    move_steps = full_move * jnp.clip(jnp.sqrt(length), rc.PACE_MIN, 1.0)
    grips = jnp.any(finger_target != finger_start, axis=-1)
    final = jnp.maximum(jnp.where(moves, move_steps, 0.0), jnp.where(grips, grip_steps, 0.0))
    return move_steps, grip_steps, jnp.maximum(jnp.ceil(jnp.max(final)), 1.0).astype(jnp.int32)


def plan_slot(
    geoms: kin.ArmGeometry,
    q: jax.Array,
    fingers: jax.Array,
    arm_ctrl: jax.Array,
    finger_ctrl: jax.Array,
    cmd: ArmCommand,
    n_substeps: int,
    paced: bool = False,
) -> Plan:
    """Plan one slot. geoms is stacked over arms; q (A, 6), fingers (A, 2) measured;
    arm_ctrl (A, 6) and finger_ctrl (A, 2) the references currently held; `n_substeps` of the
    action, `paced` its timing (`pace`)."""
    wps, arm_ok, moves, clipped, executed = jax.vmap(_plan_arm)(
        geoms, q, fingers, cmd.delta, cmd.rotvec
    )
    target = jnp.where(
        cmd.grip[:, None] == GRIP_OPEN,
        rc.FINGER_OPEN,
        jnp.where(cmd.grip[:, None] == GRIP_CLOSE, rc.FINGER_CLOSED, finger_ctrl),
    )
    move_steps, grip_steps, final = pace(
        n_substeps, paced, executed, cmd.rotvec, moves, finger_ctrl, target
    )
    return Plan(
        waypoints=wps,
        hold=arm_ctrl,
        moves=moves,
        finger_start=finger_ctrl,
        finger_target=target,
        arm_ok=arm_ok,
        ok=jnp.all(arm_ok),
        clipped=clipped,
        executed_m=executed,
        move_steps=move_steps,
        grip_steps=grip_steps,
        rest_from=final,
    )


def substeps(timestep: float) -> int:
    """Physics substeps of one action at the model's timestep."""
    return int(round(rc.ACTION_SECONDS / timestep))


ACTION_ENDS = ("fixed", "at_rest", "paced")
"""How long an action's physics runs. fixed: every action ACTION_SECONDS of substeps. at_rest:
a slot's action ends at the first substep, once its references are final (`Plan.rest_from`), where
every dof is slower than its rest speed (scene.rest_speeds); its state is the one of that substep,
whatever the other slots of the batch do, and ACTION_SECONDS bounds it. paced: as at_rest, the
move's time following its length (`pace`)."""


def ends_at_rest(action_end: str) -> bool:
    return action_end != "fixed"


def check_action_end(action_end: str) -> str:
    if action_end not in ACTION_ENDS:
        raise ValueError(f"action_end must be one of {ACTION_ENDS}, got {action_end!r}")
    return action_end


def rest_from(n_substeps: int) -> int:
    """Substeps after which every reference of an action is final (the arm at its last
    waypoint, the fingers at their target): from then on an action may end at rest."""
    return int(math.ceil(max(rc.MOVE_FRACTION, rc.GRIP_FRACTION) * n_substeps))


def _min_jerk(s: jax.Array) -> jax.Array:
    s = jnp.clip(s, 0.0, 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


def ctrl_at(plan: Plan, k: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Arm (A, 6) and finger (A, 2) references at substep k (0-based) of the action."""
    u = _min_jerk((k + 1.0) / plan.move_steps) * (rc.N_WAYPOINTS - 1)
    i = jnp.clip(jnp.floor(u).astype(jnp.int32), 0, rc.N_WAYPOINTS - 2)
    frac = (u - i)[:, None]
    arms = jnp.arange(plan.waypoints.shape[0])
    wp = plan.waypoints
    arm = wp[arms, i] + frac * (wp[arms, i + 1] - wp[arms, i])
    arm = jnp.where(plan.moves[:, None], arm, plan.hold)
    s = jnp.clip((k + 1.0) / plan.grip_steps, 0.0, 1.0)[:, None]
    fingers = plan.finger_start + s * (plan.finger_target - plan.finger_start)
    return arm, fingers
