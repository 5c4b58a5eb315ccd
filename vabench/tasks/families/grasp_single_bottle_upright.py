"""grasp_single_bottle_upright: pick up a drink bottle standing upright, right arm.

Scene (paper Table tab:seed-spec-grasp): one bottle (bottle_water.xml: 64 mm across, 168 mm
tall; it fits the 90 mm aperture with 13 mm to spare on each side) standing on its base at
x in [0.20, 0.28], y in [-0.16, -0.04], fixed upright orientation (no yaw: the 16-sided body
looks the same from every side). Its origin, the centre of the body, is 60 mm above the table.
Success: the bottle lifted more than 50 mm above its settled height and the right gripper
closed (both now, not latched). Budget 50 steps.
Checkpoints: reached (GC within 30 mm of the body's centre), grasped (closed and touching),
lifted (> 50 mm), completed (success).
Expert: side grasp: approach horizontal along +y with the fingers closing along world x; line
up in x above the bottle, come to 20 mm in front of the body's centre, descend to its height
(the open fingers straddle the bottle), slide in, close, lift 100 mm.
"""

from __future__ import annotations

from dataclasses import dataclass

from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import OnTable, Script
from vabench.tasks.expert import ExpertContext
from vabench.tasks.grasp_place import GraspFamily

BOTTLE_AT = OnTable(x=(0.20, 0.28), y=(-0.16, -0.04), half_h=sk.BOTTLE_HALF_H)
"""The upright bottle (its origin, the body's centre, above the table) of this family and of
place_single_bottle_upright; the held-out variants stand a taller container there."""


@dataclass(frozen=True)
class GraspSingleBottleUpright(GraspFamily):
    def grasp(self, ctx: ExpertContext) -> Script:
        yield from sk.side_grasp(ctx, "right", lambda v: v.pos("bottle"))


TASK = GraspSingleBottleUpright(
    name="grasp_single_bottle_upright",
    instruction="Pick up the upright bottle and lift it off the table.",
    objects=(("bottle", "bottle_water.xml"),),
    on_table=(("bottle", BOTTLE_AT),),
)
