"""click_bell_right: press the desk bell's button with the closed right gripper.

Scene (paper Table tab:seed-spec-functional): one desk bell resting on the table at
x in [0.12, 0.26], y in [-0.18, -0.04], upright, yaw 0 (the paper draws no yaw; the bell is
round). Two bell model ids (`bell_a.xml`: brass dome on a thin black base; `bell_b.xml`: the
same dome in silver on a taller, narrower red base), same structure (MJX shares mesh data between
slots, so the dome mesh is common): a base, a dome, and a push button whose flat
cap sits on a spring-loaded plunger (16 mm travel; it absorbs an overshooting press, which would
otherwise squeeze the rigid bell between a stiff arm and the table and launch it).
The bell's functional point (press point) is the top centre of the cap at rest, 76 mm above the
bell's origin (the centre of its base's bottom) in both variants, so the predicate needs no
variant id: press = p_bell + R_bell (0, 0, 0.076).
Success (latched, FACTS): once, after some action, the right gripper is closed, it touches the
bell (watched contact pair bell / right_gripper), and the contact point, taken as the fingertip
midpoint `SlotState.tip`, lies within 25 mm of the press point in x and in y and within 30 mm
in z. The latch "pressed" is success from then on. Budget 50 steps.
Checkpoints: gripper_closed (closed now), aligned (closed, fingertips within 25 mm of the press
point in x and y), completed.
Expert: close the gripper, turn it to point straight down, bring the fingertips 50 mm above the
press point, lower them 6 mm past the cap's top (the plunger gives way).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from vabench.tasks.base import (
    TIP_BEYOND_GC,
    Evaluation,
    ObjectIndex,
    OnTable,
    Sample,
    Script,
    SlotState,
    Task,
)
from vabench.tasks.expert import ExpertContext, nearest, yaw_candidates

BELL_AT = OnTable(x=(0.12, 0.26), y=(-0.18, -0.04))  # its origin: the centre of its base's bottom
PRESS_OFFSET = np.array([0.0, 0.0, 0.076])  # button top in the bell frame (both variants)
XY_TOL, Z_TOL = 0.025, 0.030
VARIANT_FILES = ("bell_a.xml", "bell_b.xml")

HOVER = 0.05
PUSH = 0.006


def press_point(ix: ObjectIndex, qpos: jax.Array) -> jax.Array:
    return ix.pos(qpos, "bell") + ix.mat(qpos, "bell") @ jnp.asarray(PRESS_OFFSET)


@dataclass(frozen=True)
class ClickBellRight(Task):
    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        r = self.arm("right")
        err = jnp.abs(s.tip(r) - press_point(ix, s.qpos))
        xy_ok = jnp.all(err[:2] <= XY_TOL)
        z_ok = err[2] <= Z_TOL
        closed = ~s.grip_open[r]
        touching = self.contact(s, "bell", "right_gripper")
        pressed = self.latch(latched, "pressed") | (closed & touching & xy_ok & z_ok)
        checks = {
            "gripper_closed": closed,
            "contact": touching,
            "xy_within_tolerance": xy_ok,
            "z_within_tolerance": z_ok,
            "pressed": pressed,
        }
        return Evaluation(
            checks=checks,
            latched=jnp.array([pressed]),
            subgoals=jnp.array([closed, closed & xy_ok]),
            success=pressed,
        )

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from ctx.grip("right", close=True)
        goal = nearest(ctx.view.arms["right"].rot, yaw_candidates(0.0, 90.0))
        yield from ctx.rotate_to("right", goal)
        press = ctx.view.pos("bell") + ctx.view.mat("bell") @ PRESS_OFFSET
        above = press + [0.0, 0.0, TIP_BEYOND_GC + HOVER]
        yield from ctx.move_to("right", above, order="zxy")
        yield from ctx.move_to("right", above, order="xyz")
        yield ctx.move("right", "z", -(HOVER + PUSH) * 1000.0)


TASK = ClickBellRight(
    name="click_bell_right",
    instruction="Press the button on top of the bell with the closed right gripper.",
    arms=("right",),
    step_budget=50,
    checkpoints=("gripper_closed", "aligned", "completed"),
    latches=("pressed",),
    contact_pairs=(("bell", "right_gripper"),),
    objects=(("bell", VARIANT_FILES),),
    on_table=(("bell", BELL_AT),),
    variants=("bell_a", "bell_b"),
)
