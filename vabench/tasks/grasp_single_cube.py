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

import jax
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task, yaw_quat
from vabench.tasks.expert import ExpertContext
from vabench.tasks.objects import attach_object

CUBE_HALF = 0.025
X_RANGE, Y_RANGE, YAW_DEG = (0.18, 0.26), (-0.16, -0.06), (-45.0, 45.0)


def sample_cube(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The cube pose of grasp_single_cube (shared with place_single_cube)."""
    x = rng.uniform(*X_RANGE)
    y = rng.uniform(*Y_RANGE)
    yaw = np.radians(rng.uniform(*YAW_DEG))
    return np.array([x, y, rc.TABLE_Z + CUBE_HALF]), yaw_quat(yaw)


@dataclass(frozen=True)
class GraspSingleCube(Task):
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, "cube_red_50.xml", "cube")

    def sample(self, seed: int) -> Sample:
        return Sample({"cube": sample_cube(self.rng(seed))})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        return common.grasp_evaluation(self, ix, s, latched, "cube")

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from common.topdown_grasp(ctx, "right", "cube")
        yield from common.lift(ctx, "right", 0.10)


TASK = GraspSingleCube(
    name="grasp_single_cube",
    instruction="Pick up the red cube and lift it off the table.",
    arms=("right",),
    step_budget=50,
    checkpoints=common.GRASP_CHECKPOINTS,
    contact_pairs=(("cube", "right_gripper"),),
)
