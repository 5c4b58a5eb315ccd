"""beat_block_hammer_right: pick up the hammer and strike the block's top with its head.

Scene (paper Table tab:seed-spec-functional): a light claw hammer (`hammer.xml`: a 200 mm oval
wooden handle and a 95 mm steel head, 0.12 kg) lying on its side, its origin (mid-handle, on the
handle's axis) at x in [0.02, 0.06], y in [-0.10, -0.04], the handle along +x with the head at
the far end, the striking face pointing -y; a red 0.05 m steel block (cube, 0.5 kg) at
x in [0.14, 0.22], y in [0.06, 0.13]. The paper's yaw in [-0.5, 0.5] rad is the block's (as in
RoboTwin, which places the hammer in a fixed orientation and randomises the block's yaw); the
hammer's yaw is 0.
Success (all now, plus one latch), as the paper's row ("Hammer lifted with contact by
>40 mm; ... physical hammer-block contact; gripper closed"):
- lifted: the hammer was lifted > 40 mm above its settled height while held (right gripper
  closed and touching it) at some point (latched);
- gripper_closed: the right gripper closed;
- held: ... and touching the hammer: the row's "with contact" holds at the strike too, so a
  hammer that left the fingers (thrown, dropped) and lands on the block does not pass;
- aligned: the hammer's functional point, the centre of the striking face, p_h + R_h
  (0.115, -0.05, 0), within 20 mm (strictly) in x and in y of the block's top centre,
  p_b + R_b (0, 0, 0.025); computed from the hammer's pose, so any hammer orientation counts;
- contact: physical hammer-block contact.
Budget 100 steps.
Checkpoints: reached (GC within 30 mm of the handle's grasp point, on its axis 45 mm from the origin
towards the head), grasped (closed and touching), lifted (latched), aligned (while held),
completed.
Expert: top-down grasp across the handle 70 mm behind the face (the palm then stays clear of the
block), lift 100 mm, carry the hammer flat until the face centre is above the block's top
centre with the head's underside 30 mm above the block, lower it to 2 mm above, then in 2 mm
steps until the head touches (a stiff arm pressing far into an object launches it). RoboTwin's
expert likewise lowers the functional point onto the block without turning the hammer.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task, yaw_quat
from vabench.tasks.expert import ExpertContext, topdown

HAMMER_X, HAMMER_Y = (0.02, 0.06), (-0.10, -0.04)
BLOCK_X, BLOCK_Y, BLOCK_YAW = (0.14, 0.22), (0.06, 0.13), (-0.5, 0.5)
HAMMER_REST = 0.017  # origin above the table when lying on its side
BLOCK_HALF = 0.025
FACE = np.array([0.115, -0.05, 0.0])  # functional point in the hammer frame
GRASP = np.array([0.045, 0.0, 0.0])  # handle axis, 70 mm behind the face

LIFT_TOL = 0.04  # lifted > 40 mm
XY_TOL = 0.02  # functional point x/y error < 20 mm

HOVER = 0.08
HEAD_HALF = 0.017  # half the head's thickness
LIFT = 0.10
STRIKE_ABOVE = 0.03
STRIKE_STEP = 0.002


@dataclass(frozen=True)
class BeatBlockHammerRight(Task):
    def sample(self, seed: int) -> Sample:
        rng = self.rng(seed)
        hammer = np.array(
            [rng.uniform(*HAMMER_X), rng.uniform(*HAMMER_Y), rc.TABLE_Z + HAMMER_REST]
        )
        block = np.array([rng.uniform(*BLOCK_X), rng.uniform(*BLOCK_Y), rc.TABLE_Z + BLOCK_HALF])
        block_yaw = rng.uniform(*BLOCK_YAW)
        return Sample({"hammer": (hammer, yaw_quat(0.0)), "block": (block, yaw_quat(block_yaw))})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        r = self.arm("right")
        q = s.qpos
        p_h, r_h = ix.pos(q, "hammer"), ix.mat(q, "hammer")
        face = p_h + r_h @ jnp.asarray(FACE)
        top = ix.pos(q, "block") + ix.mat(q, "block") @ jnp.array([0.0, 0.0, BLOCK_HALF])
        closed = ~s.grip_open[r]
        held = common.holding(s, r, self.contact(s, "hammer", "right_gripper"))
        lifted = self.latch(latched, "lifted") | (held & (ix.lift(s, "hammer") > LIFT_TOL))
        aligned = jnp.all(jnp.abs(face[:2] - top[:2]) < XY_TOL)
        touching = self.contact(s, "hammer", "block")
        checks = {
            "lifted": lifted,
            "gripper_closed": closed,
            "held": held,
            "aligned": aligned,
            "contact": touching,
        }
        subgoals = jnp.array(
            [
                common.near(s, r, p_h + r_h @ jnp.asarray(GRASP)),
                held,
                lifted,
                held & aligned,
            ]
        )
        return Evaluation(
            checks=checks,
            latched=jnp.array([lifted]),
            subgoals=subgoals,
            success=lifted & held & aligned & touching,
        )

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        def grasp_point(v) -> np.ndarray:
            return v.pos("hammer") + v.mat("hammer") @ GRASP

        handle_yaw = np.arctan2(ctx.view.mat("hammer")[1, 0], ctx.view.mat("hammer")[0, 0])
        # fingers across the handle
        yield from ctx.rotate_to("right", topdown(handle_yaw - np.pi / 2))
        above = lambda v: grasp_point(v) + [0.0, 0.0, HOVER]  # noqa: E731
        yield from ctx.move_to("right", above, order="zxy")
        yield from ctx.move_to("right", above, order="xyz")
        # GC 4 mm above the handle's axis keeps the fingertips clear of the table
        yield from ctx.move_to("right", lambda v: grasp_point(v) + [0.0, 0.0, 0.004], order="zxy")
        yield from ctx.grip("right", close=True)
        yield from common.lift(ctx, "right", LIFT)

        def face_at(height: float):
            """GC target putting the face centre `height` above the block's top centre."""

            def target(v) -> np.ndarray:
                face = v.pos("hammer") + v.mat("hammer") @ FACE
                top = v.pos("block") + v.mat("block") @ [0.0, 0.0, BLOCK_HALF]
                return v.arms["right"].gc + (top + [0.0, 0.0, height]) - face

            return target

        # the head lies on its side: its underside is HEAD_HALF below the face centre
        yield from ctx.move_to("right", face_at(HEAD_HALF + STRIKE_ABOVE), order="zxy", tol_mm=2.0)
        yield from ctx.move_to("right", face_at(HEAD_HALF + STRIKE_ABOVE), order="xyz", tol_mm=2.0)
        # strike: most of the way in one move, then millimetre steps until the head touches
        yield ctx.move("right", "z", -(STRIKE_ABOVE - STRIKE_STEP) * 1000.0)
        for _ in range(4):
            yield ctx.move("right", "z", -STRIKE_STEP * 1000.0)


TASK = BeatBlockHammerRight(
    name="beat_block_hammer_right",
    instruction="Pick up the hammer and strike the top of the red block with the hammer's head.",
    step_budget=100,
    checkpoints=("reached", "grasped", "lifted", "aligned", "completed"),
    objects=(("hammer", "hammer.xml"), ("block", "block_red_steel.xml")),
    latches=("lifted",),
    contact_pairs=(("hammer", "right_gripper"), ("hammer", "block")),
)
