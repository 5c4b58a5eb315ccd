"""grasp_single_bottle: pick up a drink bottle lying on its side with the right arm.

Scene (paper Table tab:seed-spec-grasp): one bottle (bottle_water.xml: 64 mm across, 168 mm
tall, blue body with a yellow label and a red cap) lying on its side with its centre at
x in [0.20, 0.28], y in [-0.16, -0.04], yaw in [-22.5, 22.5] deg. Yaw is the heading of the
bottle's axis measured from world +x: at yaw 0 it lies left-right, cap to the right. The body
is a 16-sided prism lying on one of its flat faces (centre 31.4 mm above the table), so it does
not roll away (the reset gate rejects objects turning > 3 deg while settling).
Success: the bottle lifted more than 50 mm above its settled height and the right gripper
closed (both now, not latched). Budget 50 steps.
Checkpoints: reached (GC within 30 mm of the body's centre), grasped (closed and touching),
lifted (> 50 mm), completed (success).
Expert: fingers straight down and closing across the body, GC at the body's centre, close,
lift 100 mm.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import Sample, Script
from vabench.tasks.expert import ExpertContext
from vabench.tasks.grasp_place import GraspFamily

X_RANGE, Y_RANGE, YAW_DEG = (0.20, 0.28), (-0.16, -0.04), (-22.5, 22.5)


@dataclass(frozen=True)
class GraspSingleBottle(GraspFamily):
    """The family; its held-out variant changes the container (`objects`, `lying_pose`)."""

    lying_pose: Callable[[float, float, float], tuple[np.ndarray, np.ndarray]] = (
        sk.lying_bottle_pose
    )  # the container's pose on the table at (x, y, yaw)

    def sample(self, seed: int) -> Sample:
        rng = self.rng(seed)
        x, y = rng.uniform(*X_RANGE), rng.uniform(*Y_RANGE)
        yaw = np.radians(rng.uniform(*YAW_DEG))
        return Sample({"bottle": self.lying_pose(x, y, yaw)})

    def grasp(self, ctx: ExpertContext) -> Script:
        yield from sk.grasp_across(ctx, "right", "bottle", long_axis=2)


TASK = GraspSingleBottle(
    name="grasp_single_bottle",
    instruction="Pick up the bottle lying on the table and lift it off the table.",
    objects=(("bottle", "bottle_water.xml"),),
)
