"""Building blocks shared by families: the grasp and the place-on-target predicates of the
paper's tables, and the expert skills (top-down grasp, carry and release) built on the
primitives of `vabench.tasks.expert`."""

from __future__ import annotations

from collections.abc import Iterator

import jax
import jax.numpy as jnp
import numpy as np

from vabench.tasks.base import LIFT_M, Evaluation, ObjectIndex, SlotState, Task
from vabench.tasks.expert import Action, ExpertContext, nearest, yaw_candidates, yaw_of

GRASP_CHECKPOINTS = ("reached", "grasped", "lifted", "completed")
PLACE_CHECKPOINTS = ("reached", "grasped", "lifted", "transported", "released", "completed")
REACH_M = 0.03  # "reached": GC within 30 mm of the object's grasp point


def near(s: SlotState, arm: int, point: jax.Array, radius: float = REACH_M) -> jax.Array:
    return jnp.linalg.norm(s.gc[arm] - point) < radius


def holding(s: SlotState, arm: int, touching: jax.Array) -> jax.Array:
    """Closed gripper touching the object (the "grasped" checkpoint)."""
    return ~s.grip_open[arm] & touching


def lifted(ix: ObjectIndex, s: SlotState, obj: str, by: float = LIFT_M) -> jax.Array:
    return ix.lift(s, obj) > by


def grasp_evaluation(
    task: Task, ix: ObjectIndex, s: SlotState, latched: jax.Array, obj: str
) -> Evaluation:
    """The grasp predicate of tab:seed-spec-grasp: lifted > 50 mm and the right gripper closed.

    The paper's row asks for no contact, so none is tested here (contact only moves the
    "grasped" checkpoint): a thrown object would pass this row, and it is the physics that must
    not throw one (assets/scene/table.xml; tests/test_grasp_hold.py checks every grasping
    family's retained seeds). The hammer's row does say "with contact", and its predicate
    tests it."""
    r = task.arm("right")
    up = lifted(ix, s, obj)
    closed = ~s.grip_open[r]
    subgoals = jnp.array(
        [
            near(s, r, ix.pos(s.qpos, obj)),
            holding(s, r, task.contact(s, obj, "right_gripper")),
            up,
        ]
    )
    return Evaluation(
        checks={"lifted": up, "gripper_closed": closed},
        latched=latched,
        subgoals=subgoals,
        success=up & closed,
    )


def place_evaluation(
    task: Task,
    ix: ObjectIndex,
    s: SlotState,
    latched: jax.Array,
    obj: str,
    target: str,
    placement: dict[str, jax.Array],
    target_still: tuple[str, jax.Array],
) -> Evaluation:
    """The predicate every right-arm place family shares: `obj` was lifted >= 50 mm at some
    point (the task's "was_lifted" latch), every family-specific `placement` check holds, the
    target did not move (`target_still`: check name, flag), `obj` touches `target`, and the
    right gripper is open. Checkpoints reached, grasped, lifted, transported (all placement
    checks), released (open with the first, horizontal, placement check), completed."""
    r = task.arm("right")
    was_lifted = task.latch(latched, "was_lifted") | (ix.lift(s, obj) >= LIFT_M)
    placed = jnp.all(jnp.array(list(placement.values())))
    horizontal = next(iter(placement.values()))
    still_name, still = target_still
    touching = task.contact(s, obj, target)
    opened = s.grip_open[r]
    checks = {
        "was_lifted": was_lifted,
        **placement,
        still_name: still,
        "contact": touching,
        "gripper_open": opened,
    }
    subgoals = jnp.array(
        [
            near(s, r, ix.pos(s.qpos, obj)),
            holding(s, r, task.contact(s, obj, "right_gripper")),
            was_lifted,
            placed,
            opened & horizontal,
        ]
    )
    success = was_lifted & placed & still & touching & opened
    return Evaluation(
        checks=checks, latched=jnp.array([was_lifted]), subgoals=subgoals, success=success
    )


# -- expert skills ---------------------------------------------------------------------------
def topdown_grasp(
    ctx: ExpertContext,
    arm: str,
    obj: str,
    symmetry_deg: float = 90.0,
    grasp_dz: float = 0.0,
    hover: float = 0.08,
    yaw_offset: float = 0.0,
) -> Iterator[Action]:
    """Turn the fingers across the object (top-down), hover above it, descend so that GC sits
    `grasp_dz` above the object's origin, close."""
    yaw = yaw_of(ctx.view.mat(obj)) + yaw_offset
    goal = nearest(ctx.view.arms[arm].rot, yaw_candidates(yaw, symmetry_deg))
    yield from ctx.rotate_to(arm, goal)
    yield from ctx.move_to(arm, lambda v: v.pos(obj) + [0.0, 0.0, hover], order="zxy")
    yield from ctx.move_to(arm, lambda v: v.pos(obj) + [0.0, 0.0, hover], order="xyz")
    yield from ctx.move_to(arm, lambda v: v.pos(obj) + [0.0, 0.0, grasp_dz], order="zxy")
    yield from ctx.grip(arm, close=True)


def lift(ctx: ExpertContext, arm: str, dz: float = 0.10) -> Iterator[Action]:
    goal = ctx.view.arms[arm].gc + [0.0, 0.0, dz]
    yield from ctx.move_to(arm, goal, order="z")


def carry_and_release(
    ctx: ExpertContext,
    arm: str,
    obj: str,
    target_xy: np.ndarray,
    rest_z: float,
    clearance: float = 0.06,
    drop: float = 0.0,
) -> Iterator[Action]:
    """Carry the held object over target_xy at `clearance` above its resting height, lower it
    until its origin is `drop` above `rest_z` (0: resting on the target while still held, so
    nothing falls or bounces when the fingers open), open, and back off upwards."""

    def offset() -> np.ndarray:
        return ctx.view.arms[arm].gc - ctx.view.pos(obj)  # the grasp, as it is now

    yield from ctx.move_to(
        arm, lambda v: np.r_[v.pos(obj)[:2], rest_z + clearance] + offset(), order="z"
    )
    yield from ctx.move_to(
        arm, lambda v: np.r_[target_xy, rest_z + clearance] + offset(), order="xyz"
    )
    yield from lower_until_resting(ctx, arm, obj, rest_z + drop)
    yield from ctx.grip(arm, close=False)
    yield from lift(ctx, arm, 0.05)


def lower_until_resting(
    ctx: ExpertContext, arm: str, obj: str, z: float, tol: float = 0.001, max_steps: int = 6
) -> Iterator[Action]:
    """Lower the held object until its origin is at `z`, or until it stops following the
    gripper (it met its support early: a slightly tilted grasp, a soft contact) or the planner
    refuses to go lower; then the object rests and the caller can let go."""
    for _ in range(max_steps):
        obj0, gc0 = ctx.view.pos(obj)[2], ctx.view.arms[arm].gc[2]
        err = z - obj0
        if abs(err) < tol:
            return
        yield ctx.move(arm, "z", err * 1000.0)
        last = ctx.view.last
        if last is not None and not last.planner_success:
            return  # the gripper is as low as it may go
        moved_obj = ctx.view.pos(obj)[2] - obj0
        moved_gc = ctx.view.arms[arm].gc[2] - gc0
        if moved_gc < -tol and moved_obj > 0.5 * moved_gc:
            return  # blocked: resting on the support
