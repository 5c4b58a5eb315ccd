"""grasp_single_bottle_heldout: the held-out container of grasp_single_bottle (transfer track).

What is held out: the container. Instead of the base's round water bottle (bottle_water.xml:
64 mm across, 168 mm tall, blue with a yellow label and a red cap) the scene holds a flat
shampoo bottle with a pump (bottle_shampoo.xml: rounded-rectangle section 56 mm wide x 38 mm
thick, body 160 mm long, 205 mm overall; magenta, white label, black pump), lying on a broad face
with its centre 19 mm above the table (the base's bottle: 31.4 mm).
Scene: the base's ranges, drawn from the variant's own seed stream (`heldout_rng`): centre at
x in [0.20, 0.28], y in [-0.16, -0.04], yaw in [-22.5, 22.5] deg, yaw being the heading of the
bottle's axis from world +x (at yaw 0 it lies left-right, pump to the right).
Success (the base's predicate, unchanged): the bottle lifted more than 50 mm above its settled
height and the right gripper closed (both now, not latched). Instruction, arm and budget (50
steps) are the base's.
Checkpoints: reached (GC within 30 mm of the body's centre), grasped (closed and touching),
lifted (> 50 mm), completed (success).
Expert: fingers straight down and closing across the body's width (its flat narrow sides), GC
at the body's centre, close, lift 100 mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vabench.tasks import skills_heldout_bottles as hb
from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import Script
from vabench.tasks.expert import ExpertContext, View
from vabench.tasks.families.grasp_single_bottle import TASK as BASE
from vabench.tasks.families.grasp_single_bottle import GraspSingleBottle
from vabench.tasks.heldout import variant


@dataclass(frozen=True)
class GraspSingleBottleHeldout(GraspSingleBottle):
    """The base family with the expert's grasp across the flat bottle's width."""

    def grasp(self, ctx: ExpertContext) -> Script:
        across = sk.axis_heading(ctx.view.mat("bottle"), 0)  # the width, local x

        def centre(v: View) -> np.ndarray:  # never below the lowest top-down GC allowed
            p = v.pos("bottle")
            return np.r_[p[:2], max(p[2], sk.TOPDOWN_MIN_GC_Z + 0.001)]

        yield from sk.topdown_grasp_at(ctx, "right", centre, across)


TASK = variant(
    BASE,
    "grasp_single_bottle_heldout",
    GraspSingleBottleHeldout,
    objects=(("bottle", "bottle_shampoo.xml"),),
    lying_pose=hb.lying_shampoo_pose,
    seed_stream=hb.heldout_rng,
)
