"""place_single_bottle_upright_heldout: the held-out container of place_single_bottle_upright
(transfer track).

What is held out: the container, the same as grasp_single_bottle_upright_heldout's: a tall
square-section bottle (bottle_square.xml: 50 x 50 mm, body 180 mm, 220 mm overall; orange,
purple label, white cap) instead of the round water bottle (64 mm across, 168 mm tall).
Scene: the base's ranges, drawn from the variant's own seed stream (`heldout_rng`): the bottle
upright at x in [0.20, 0.28], y in [-0.16, -0.04] (faces normal to world x and y); the base's
green pad (pad_green_130.xml, half-size 0.065 m, 3 mm half-thick) at x in [0.03, 0.09], y in
[0.07, 0.13], axis-aligned.
Success (the base's predicate and tolerances; only the resting height follows the container):
the bottle was lifted >= 50 mm at some point (latched); the x and y errors of its body centre to
the pad centre each <= 40 mm; its height error to the upright resting height on the pad (pad
half-thickness + 90 mm) <= 35 mm; the pad displaced <= 2 mm; bottle-pad contact; right gripper
open. Instruction, arm and budget (100 steps) are the base's. Unlike the base (where a bottle
lying on the pad passes the height check), this container lying on the pad has its centre 25 mm
above the pad's top, 65 mm below the upright resting height, and fails it.
Checkpoints: reached, grasped, lifted (latched), transported (x/y and height within
tolerance), released (gripper open), completed.
Expert: the base's: side grasp, lift 60 mm, carry over the pad centre, lower until resting,
open, back off upwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks import skills_heldout_bottles as hb
from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task, yaw_quat
from vabench.tasks.expert import ExpertContext
from vabench.tasks.grasp_single_bottle_upright_heldout import sample_upright_square
from vabench.tasks.objects import attach_object
from vabench.tasks.place_single_bottle_upright import (
    HEIGHT_TOL,
    PAD_HALF_THICK,
    PAD_MOVE_TOL,
    PAD_X,
    PAD_Y,
    XY_TOL,
)
from vabench.tasks.place_single_bottle_upright import TASK as BASE
from vabench.tasks.place_single_cube import place_checks

REST_HEIGHT = PAD_HALF_THICK + hb.SQUARE_HALF_H  # bottle origin above the pad centre


@dataclass(frozen=True)
class PlaceSingleBottleUprightHeldout(Task):
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, "bottle_square.xml", "bottle")
        attach_object(spec, "pad_green_130.xml", "pad")

    @staticmethod
    def rng(seed: int) -> np.random.Generator:
        return hb.heldout_rng(seed)

    def sample(self, seed: int) -> Sample:
        rng = self.rng(seed)
        bottle = sample_upright_square(rng)
        pad = np.array([rng.uniform(*PAD_X), rng.uniform(*PAD_Y), rc.TABLE_Z + PAD_HALF_THICK])
        return Sample({"bottle": bottle, "pad": (pad, yaw_quat(0.0))})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        return place_checks(
            self, ix, s, latched, "bottle", "pad", REST_HEIGHT, XY_TOL, HEIGHT_TOL, PAD_MOVE_TOL
        )

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from sk.side_grasp(ctx, "right", lambda v: v.pos("bottle"))
        yield from common.lift(ctx, "right", 0.06)
        pad = ctx.view.pos("pad")
        yield from common.carry_and_release(ctx, "right", "bottle", pad[:2], pad[2] + REST_HEIGHT)


TASK = PlaceSingleBottleUprightHeldout(
    name="place_single_bottle_upright_heldout",
    instruction=BASE.instruction,
    arms=BASE.arms,
    step_budget=BASE.step_budget,
    checkpoints=common.PLACE_CHECKPOINTS,
    latches=("was_lifted",),
    contact_pairs=(("bottle", "right_gripper"), ("bottle", "pad")),
    suite="transfer",
    base_family=BASE.name,
)
