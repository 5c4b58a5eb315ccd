"""place_single_cube: put the red cube on the green pad, right arm.

Scene (paper Table tab:seed-spec-place): the cube as in grasp_single_cube (0.05 m, x in
[0.18, 0.26], y in [-0.16, -0.06], yaw in [-45, 45] deg); a green pad (half-size 0.06 m, 3 mm
half-thick, FACTS) at x in [0.10, 0.14], y in [0, 0.04], axis-aligned.
Success (all now, plus one latch): the cube was lifted >= 50 mm at some point (latched); its x
and y errors to the pad centre each <= 35 mm; its height error to the resting height on the pad
<= 35 mm; the pad displaced <= 2 mm; cube-pad contact; right gripper open. Budget 100 steps.
Checkpoints: reached, grasped, lifted (latched), transported (x/y within tolerance),
released (gripper open), completed.
Expert: top-down grasp, lift, carry over the pad centre, lower to 4 mm above resting, open.
"""

from __future__ import annotations

from dataclasses import dataclass

from vabench.tasks import common
from vabench.tasks.base import OnTable, Sample, Script
from vabench.tasks.expert import ExpertContext
from vabench.tasks.families.grasp_single_cube import CUBE_AT, CUBE_HALF
from vabench.tasks.grasp_place import PadPlaceFamily

PAD_HALF_THICK = 0.003
PAD_AT = OnTable(x=(0.10, 0.14), y=(0.0, 0.04), half_h=PAD_HALF_THICK)


@dataclass(frozen=True)
class PlaceSingleCube(PadPlaceFamily):
    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from common.topdown_grasp(ctx, "right", "cube")
        yield from common.lift(ctx, "right", 0.06)
        pad = ctx.view.pos("pad")
        yield from common.carry_and_release(
            ctx, "right", "cube", pad[:2], pad[2] + PAD_HALF_THICK + CUBE_HALF
        )


TASK = PlaceSingleCube(
    name="place_single_cube",
    instruction="Pick up the red cube and place it on the green pad.",
    step_budget=100,
    objects=(("cube", "cube_red_50.xml"), ("pad", "pad_green.xml")),
    on_table=(("cube", CUBE_AT), ("pad", PAD_AT)),
    rest_height=PAD_HALF_THICK + CUBE_HALF,
    xy_tol=0.035,
    height_tol=0.035,
    pad_move_tol=0.002,
)
