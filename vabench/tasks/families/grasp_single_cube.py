"""grasp_single_cube: pick up a 5 cm red cube with the right arm.

Scene (paper Table tab:seed-spec-grasp): one red 0.05 m cube resting on the table at
x in [0.18, 0.26], y in [-0.16, -0.06], yaw in [-45, 45] deg.
Success: the cube lifted more than 50 mm above its settled height and the right gripper closed
(both now, not latched). Budget 50 steps.
Checkpoints: reached (GC within 30 mm of the cube centre), grasped (closed and touching),
lifted (> 50 mm), completed (success).
Expert: top-down grasp across the cube's faces, GC at the cube centre, close, lift 100 mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vabench.tasks import common
from vabench.tasks.base import ObjectPoses, OnTable, Script
from vabench.tasks.expert import ExpertContext
from vabench.tasks.grasp_place import GraspFamily
from vabench.tasks.heldout import NO_DISTRACTORS, Distractors

CUBE_HALF = 0.025
CUBE_AT = OnTable(x=(0.18, 0.26), y=(-0.16, -0.06), half_h=CUBE_HALF, yaw_deg=(-45.0, 45.0))
"""The cube of grasp_single_cube (and of place_single_cube)."""


@dataclass(frozen=True)
class GraspSingleCube(GraspFamily):
    """The family; its held-out variant changes the data below (and the objects)."""

    symmetry_deg: float = 90.0  # of the top-down grasp: the cube's faces
    distractors: Distractors = NO_DISTRACTORS

    def draw(self, rng: np.random.Generator) -> ObjectPoses:
        poses = super().draw(rng)  # the cube, then the distractors around it
        return {**poses, **self.distractors.sample(rng, poses["cube"][0])}

    def grasp(self, ctx: ExpertContext) -> Script:
        yield from common.topdown_grasp(ctx, "right", "cube", symmetry_deg=self.symmetry_deg)


TASK = GraspSingleCube(
    name="grasp_single_cube",
    instruction="Pick up the red cube and lift it off the table.",
    objects=(("cube", "cube_red_50.xml"),),
    on_table=(("cube", CUBE_AT),),
)
