"""handover_horizontal_block: hand a lying block from the arm on its side to the other arm.

Scene (paper Table tab:seed-spec-dual, FACTS.md): one orange 0.03 x 0.03 x 0.20 m block
(`assets/objects/block_orange_200.xml`, long axis = its body z axis) lying on the table with its
long axis along world y, centre at x in [-0.20, -0.15] U [0.15, 0.20] (side drawn first, fair
coin; then x uniform on that side), y in [-0.05, 0]. The paper gives no yaw: it is fixed.
Giver = the arm on the block's side (x > 0: right), receiver = the other; stored in
`Sample.params` ("giver", "receiver") and recomputed by the predicate from the block's settled
initial x, so the jitted predicate needs no per-seed input.
Latched chain (FACTS.md), each link counting only after the earlier ones, all latched:
  giver_grasped     giver closed and touching the block;
  presented         giver_grasped, the giver still holding the block (closed, touching), the
                    block lifted >= 50 mm above its settled height and its long axis within
                    20 deg of vertical;
  receiver_grasped  presented, receiver closed and touching the block while the giver still
                    holds it (a drop and catch is no handover);
  giver_released    receiver_grasped, giver open.
Success (now): chain completed (giver_released latched); giver open and receiver closed; block
centre z > 0.92 m; block centre on the receiver's side (x sign: receiver left -> x < 0); long
axis within 20 deg of vertical. Budget 100 steps.
Checkpoints: the four links in order, then completed.
Expert: the giver grasps the block top-down across its middle, lifts it, turns its gripper
about the closing axis until the approach points forward (+y), which stands the block upright
in its fingers, and presents it just on the receiver's side of x = 0 with the block centre at
0.95 m; the receiver grasps the block's upper end top-down, the giver opens and backs off,
and the receiver carries the block further to its side.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks.base import (
    LIFT_M,
    TIP_BEYOND_GC,
    Evaluation,
    ObjectIndex,
    Sample,
    Script,
    SlotState,
    Task,
)
from vabench.tasks.expert import ExpertContext, View, nearest, topdown

HALF = (0.015, 0.015, 0.10)
X_ABS, Y_RANGE = (0.15, 0.20), (-0.05, 0.0)
LYING_QUAT = np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0])  # long axis along -y
MIN_Z = 0.92
MAX_TILT_DEG = 20.0
COS_TILT = float(np.cos(np.radians(MAX_TILT_DEG)))
# Expert: handover point (block centre), grasp heights.
HANDOVER_X, HANDOVER_Y, HANDOVER_Z = 0.04, -0.05, 0.95
RECEIVER_BELOW_TOP = 0.025  # receiver GC this far below the block's top end
FINAL_X = 0.10


def vertical(r: jax.Array) -> jax.Array:
    """Long axis (body z) within 20 deg of the world vertical, either end up."""
    return jnp.abs(r[2, 2]) >= COS_TILT


@dataclass(frozen=True)
class HandoverHorizontalBlock(Task):
    def sample(self, seed: int) -> Sample:
        rng = self.rng(seed)
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        x = side * rng.uniform(*X_ABS)
        y = rng.uniform(*Y_RANGE)
        giver = "right" if x > 0 else "left"
        receiver = "left" if giver == "right" else "right"
        pose = (np.array([x, y, rc.TABLE_Z + HALF[0]]), LYING_QUAT.copy())
        return Sample({"block": pose}, params={"giver": giver, "receiver": receiver})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        left, right = self.arm("left"), self.arm("right")
        giver_right = s.init_qpos[ix.adr["block"]] > 0
        giver = jnp.where(giver_right, right, left)
        receiver = jnp.where(giver_right, left, right)
        touching = jnp.stack(
            [self.contact(s, "block", f"{a}_gripper") for a in self.arms]
        )  # indexed like self.arms
        holds = ~s.grip_open & touching
        p, r = ix.pos(s.qpos, "block"), ix.mat(s.qpos, "block")
        upright = vertical(r)

        grasped = latched[0] | holds[giver]
        presented = latched[1] | (
            grasped & holds[giver] & (ix.lift(s, "block") >= LIFT_M) & upright
        )
        received = latched[2] | (presented & holds[receiver] & holds[giver])
        released = latched[3] | (received & s.grip_open[giver])

        high = p[2] > MIN_Z
        receiver_side = jnp.where(giver_right, p[0] < 0, p[0] > 0)
        giver_open, receiver_closed = s.grip_open[giver], ~s.grip_open[receiver]
        checks = {
            "chain_completed": released,
            "giver_open": giver_open,
            "receiver_closed": receiver_closed,
            "high": high,
            "receiver_side": receiver_side,
            "vertical": upright,
        }
        chain = jnp.array([grasped, presented, received, released])
        success = released & giver_open & receiver_closed & high & receiver_side & upright
        return Evaluation(checks=checks, latched=chain, subgoals=chain, success=success)

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        giver, receiver = sample.params["giver"], sample.params["receiver"]
        side = -1.0 if receiver == "left" else 1.0

        # Giver: top-down across the block's middle (fingers along x), lift.
        goal = nearest(ctx.view.arms[giver].rot, [topdown(0.0), topdown(np.pi)])
        yield from ctx.rotate_to(giver, goal)
        grasp_dz = rc.TABLE_CLEARANCE + TIP_BEYOND_GC - HALF[0] + 0.004

        def centre(dz: float):
            return lambda v: v.pos("block") + [0.0, 0.0, dz]

        yield from ctx.move_to(giver, centre(0.08), order="zxy")
        yield from ctx.move_to(giver, centre(0.08), order="xyz")
        yield from ctx.move_to(giver, centre(grasp_dz), order="z")
        yield from ctx.grip(giver, close=True)
        yield from common.lift(ctx, giver, HANDOVER_Z - ctx.view.arms[giver].gc[2])

        # Stand the block up: turn about the closing axis until the approach points forward
        # (+y): rotate_local ry in two 45 deg actions (rotate_to's Euler split is degenerate at
        # 90 deg, and the planner refuses some single 90 deg turns it accepts in two halves).
        rz = ctx.view.arms[giver].rot[:, 2]
        for _ in range(2):
            yield ctx.rotate(giver, "ry", -45.0 if rz[1] > 0 else 45.0)
            ctx._check("stand up")

        def handover(v: View) -> np.ndarray:
            offset = v.arms[giver].gc - v.pos("block")
            return np.array([side * HANDOVER_X, HANDOVER_Y, HANDOVER_Z]) + offset

        yield from ctx.move_to(giver, handover, order="zxy")

        # Receiver: top-down over the block's upper end.
        def top(dz: float):
            def target(v: View) -> np.ndarray:
                axis = v.mat("block")[:, 2] * np.sign(v.mat("block")[2, 2])
                return v.pos("block") + axis * HALF[2] + [0.0, 0.0, dz]

            return target

        cands = [topdown(k * np.pi / 2) for k in range(4)]
        yield from ctx.rotate_to(receiver, nearest(ctx.view.arms[receiver].rot, cands))
        yield from ctx.move_to(receiver, top(0.08), order="zxy")
        yield from ctx.move_to(receiver, top(0.08), order="xyz")
        yield from ctx.move_to(receiver, top(-RECEIVER_BELOW_TOP), order="z")
        yield from ctx.grip(receiver, close=True)
        yield from ctx.grip(giver, close=False)
        back = ctx.view.arms[giver].gc - 0.06 * ctx.view.arms[giver].rot[:, 0]
        yield from ctx.move_to(giver, back, order="y")
        goal_x = np.array([side * FINAL_X, 0.0, 0.0])
        yield from ctx.move_to(
            receiver, lambda v: np.r_[goal_x[0], v.arms[receiver].gc[1:]], order="x"
        )


TASK = HandoverHorizontalBlock(
    name="handover_horizontal_block",
    instruction=(
        "Pick up the orange block lying on the table with the arm on its side, stand it upright "
        "and hand it over to the other arm, which keeps holding it upright on its own side."
    ),
    arms=("left", "right"),
    step_budget=100,
    checkpoints=("giver_grasped", "presented", "receiver_grasped", "giver_released", "completed"),
    latches=("giver_grasped", "presented", "receiver_grasped", "giver_released"),
    contact_pairs=(("block", "left_gripper"), ("block", "right_gripper")),
    objects=(("block", "block_orange_200.xml"),),
)
