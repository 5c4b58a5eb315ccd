"""lift_pot: lift the pot by both handles, one arm per handle.

Scene (paper Table tab:seed-spec-dual): one pot of two model ids (`assets/objects/pot_a.xml`,
`pot_b.xml`: same structure, a collision box inscribed in a visual cylinder, a visual rim and
inside, and two box handles sticking out along +-x of the pot frame; radius 0.082 / 0.090 m,
height 0.100 / 0.115 m, mass 0.60 / 0.70 kg, red / blue) at x, y in [-0.05, 0.05], yaw in
[-22.5, 22.5] deg, resting on the table. The pot frame's origin is the centre of the pot's
bottom (z = table height at rest). Both model ids put the handles' grasp points (handle
centres) at (+-0.1125, 0, 0.085) in the pot frame.
Success (all now, nothing latched): the pot origin (its bottom centre) z > 0.82 m, i.e. lifted
by more than 79 mm; each arm's GC within 30 mm of its handle's grasp point (left arm <-> the
handle on the pot's -x side, right arm <-> +x); the pot upright (pot z axis . world z > 0.8).
Budget 50 steps.
Checkpoints: reached (both GCs within 30 mm of their grasp points), grasped (both grippers
closed and touching the pot), lifted (pot origin raised more than 50 mm), completed.
Expert: each arm turns top-down with its fingers across its handle and hovers above it, both
descend to the handle centres, close together (dual_gripper.close); should a handle have
slipped out of the fingers, open and approach again (2 attempts); then lift together with
dual_gripper.move_world so the closed chain (arm, pot, arm) stays consistent.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from vabench.tasks import common
from vabench.tasks.base import Evaluation, ObjectIndex, OnTable, Sample, Script, SlotState, Task
from vabench.tasks.expert import ExpertContext, Target, View, nearest, topdown, yaw_of

POT_FILES = ("pot_a.xml", "pot_b.xml")
POT_AT = OnTable(x=(-0.05, 0.05), y=(-0.05, 0.05), yaw_deg=(-22.5, 22.5))
HANDLE = {"left": np.array([-0.1125, 0.0, 0.085]), "right": np.array([0.1125, 0.0, 0.085])}
MIN_Z = 0.82
TCP_TOL = 0.03
UPRIGHT_DOT = 0.8
LIFT_CHECKPOINT_M = 0.05
HOVER = 0.06
LIFT_BY = 0.11
GRASP_ATTEMPTS = 2
HANDLE_HALF_WIDTH = 0.012  # across the handle, where the fingers close


@dataclass(frozen=True)
class LiftPot(Task):
    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        p, r = ix.pos(s.qpos, "pot"), ix.mat(s.qpos, "pot")
        high = p[2] > MIN_Z
        near = [
            common.near(s, self.arm(a), p + r @ jnp.asarray(HANDLE[a]), TCP_TOL) for a in self.arms
        ]
        upright = r[2, 2] > UPRIGHT_DOT
        held = [
            common.holding(s, self.arm(a), self.contact(s, "pot", f"{a}_gripper"))
            for a in self.arms
        ]
        checks = {
            "pot_high": high,
            "left_at_handle": near[0],
            "right_at_handle": near[1],
            "upright": upright,
        }
        subgoals = jnp.array(
            [near[0] & near[1], held[0] & held[1], ix.lift(s, "pot") > LIFT_CHECKPOINT_M]
        )
        return Evaluation(
            checks=checks,
            latched=latched,
            subgoals=subgoals,
            success=high & near[0] & near[1] & upright,
        )

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        def handle(arm: str, dz: float = 0.0):
            def target(v: View) -> np.ndarray:
                return v.pos("pot") + v.mat("pot") @ HANDLE[arm] + [0.0, 0.0, dz]

            return target

        for _ in range(GRASP_ATTEMPTS):
            pot_yaw = yaw_of(ctx.view.mat("pot"))
            for arm in self.arms:  # fingers close across the handle: along the pot's y axis
                cands = [topdown(pot_yaw + np.pi / 2), topdown(pot_yaw - np.pi / 2)]
                yield from ctx.rotate_to(arm, nearest(ctx.view.arms[arm].rot, cands))
                yield from ctx.move_to(arm, handle(arm, HOVER), order="zxy")
                yield from ctx.move_to(arm, handle(arm, HOVER), order="xyz")
            yield from ctx.dual_move_to({arm: handle(arm) for arm in self.arms})
            yield {"action": "dual_gripper.close"}
            if all(ctx.view.arms[a].fingers.min() > HANDLE_HALF_WIDTH / 2 for a in self.arms):
                break
            yield {"action": "dual_gripper.open"}  # a handle slipped out: open and try again
            yield from ctx.dual_move_to({arm: handle(arm, HOVER) for arm in self.arms})
        lifted: dict[str, Target] = {
            arm: ctx.view.arms[arm].gc + [0.0, 0.0, LIFT_BY] for arm in self.arms
        }
        yield from ctx.dual_move_to(lifted)


TASK = LiftPot(
    name="lift_pot",
    instruction="Lift the pot off the table by holding both of its handles, one hand on each.",
    arms=("left", "right"),
    step_budget=50,
    checkpoints=("reached", "grasped", "lifted", "completed"),
    contact_pairs=(("pot", "left_gripper"), ("pot", "right_gripper")),
    objects=(("pot", POT_FILES),),
    on_table=(("pot", POT_AT),),
    variants=("pot_a", "pot_b"),
)
