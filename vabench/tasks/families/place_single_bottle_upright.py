"""place_single_bottle_upright: put the upright bottle on the green pad, right arm.

Scene (paper Table tab:seed-spec-place): the bottle as in grasp_single_bottle_upright
(bottle_water.xml, upright, x in [0.20, 0.28], y in [-0.16, -0.04]); a green pad (half-size
0.065 m, FACTS; 3 mm half-thick) at x in [0.03, 0.09], y in [0.07, 0.13], axis-aligned.
Success (all now, plus one latch; the pad predicate of `grasp_place.PadPlaceFamily`, as
place_single_cube's): the bottle was lifted >= 50 mm at some point (latched); the x and y errors
of its body centre to the pad centre each <= 40 mm; its height error to the resting height on
the pad (pad half-thickness + 60 mm) <= 35 mm; the pad displaced <= 2 mm; bottle-pad contact;
right gripper open. Budget 100 steps.
The paper's row checks no orientation: a bottle lying on the pad has its centre 31 mm above the
pad's top, 29 mm below the upright resting height, and passes the height check.
Checkpoints: reached, grasped, lifted (latched), transported (x/y and height within
tolerance), released (gripper open), completed.
Expert: side grasp as in grasp_single_bottle_upright, lift 60 mm, carry over the pad centre,
lower to 4 mm above resting, open, back off upwards.
"""

from __future__ import annotations

from dataclasses import dataclass

from vabench.tasks import common
from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import OnTable, Sample, Script
from vabench.tasks.expert import ExpertContext
from vabench.tasks.families.grasp_single_bottle_upright import BOTTLE_AT
from vabench.tasks.grasp_place import PadPlaceFamily

PAD_HALF_THICK = 0.003
PAD_AT = OnTable(x=(0.03, 0.09), y=(0.07, 0.13), half_h=PAD_HALF_THICK)


@dataclass(frozen=True)
class PlaceSingleBottleUpright(PadPlaceFamily):
    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from sk.side_grasp(ctx, "right", lambda v: v.pos("bottle"))
        yield from common.lift(ctx, "right", 0.06)
        pad = ctx.view.pos("pad")
        target_z = pad[2] + self.rest_height
        yield from common.carry_and_release(ctx, "right", "bottle", pad[:2], target_z)


TASK = PlaceSingleBottleUpright(
    name="place_single_bottle_upright",
    instruction="Pick up the bottle and place it upright on the green pad.",
    step_budget=100,
    objects=(("bottle", "bottle_water.xml"), ("pad", "pad_green_130.xml")),
    on_table=(("bottle", BOTTLE_AT), ("pad", PAD_AT)),
    rest_height=PAD_HALF_THICK + sk.BOTTLE_HALF_H,  # bottle origin above the pad centre
    xy_tol=0.040,
    height_tol=0.035,
    pad_move_tol=0.002,
)
