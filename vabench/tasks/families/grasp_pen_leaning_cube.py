"""grasp_pen_leaning_cube: pick up a marker pen leaning on a blue block, right arm.

Scene (paper Table tab:seed-spec-grasp, FACTS): the marker pen of grasp_single_pen
(pen_marker.xml, 140 mm long, 14 mm thick) leaning at a fixed 30 deg on a static 8 cm blue
block (cube_blue_80.xml, a 1.5 kg free body). The group is placed by the pen's lower end (the
centre of its lower end cap, 7 mm above the table) at x in [0.16, 0.22], y in [-0.24, -0.20];
the group's yaw in [-15, 15] deg turns the pen's heading away from +y (yaw 0: the pen rises
away from the robot, black tip down, red cap up) and the block with it. The lean is the angle
of the pen's long axis above the table (30 deg elevation; a 140 mm pen at 60 deg would rest
on the block's top edge instead): the pen's upper end rests against the block's near face,
10 mm below its top edge; it holds by friction (pen 1.6, a rubber-grip barrel) and creeps
about 2 deg (2 mm down) over the reset's 2,500 settling steps, 0.15 deg in the last 200.
Success: the pen lifted more than 50 mm above its settled height (its centre) and the right
gripper closed (both now, not latched). Budget 50 steps.
Checkpoints: reached (GC within 30 mm of the pen's centre), grasped (closed and touching),
lifted (> 50 mm), completed (success).
Expert: fingers straight down and closing across the pen's heading, GC at the pen's centre,
close, lift 100 mm (the upper end slides up the block's face and off it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import Sample, Script
from vabench.tasks.expert import ExpertContext
from vabench.tasks.grasp_place import GraspFamily

X_RANGE, Y_RANGE, YAW_DEG = (0.16, 0.22), (-0.24, -0.20), (-15.0, 15.0)
LEAN_DEG = 30.0


@dataclass(frozen=True)
class GraspPenLeaningCube(GraspFamily):
    def sample(self, seed: int) -> Sample:
        rng = self.rng(seed)
        x, y = rng.uniform(*X_RANGE), rng.uniform(*Y_RANGE)
        yaw = np.radians(rng.uniform(*YAW_DEG))
        return Sample(sk.leaning_pen_poses(x, y, yaw, np.radians(LEAN_DEG)))

    def grasp(self, ctx: ExpertContext) -> Script:
        yield from sk.grasp_across(ctx, "right", "pen", long_axis=0)


TASK = GraspPenLeaningCube(
    name="grasp_pen_leaning_cube",
    instruction="Pick up the pen leaning against the blue cube and lift it.",
    objects=(("pen", "pen_marker.xml"), ("block", "cube_blue_80.xml")),
)
