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

import jax
import mujoco
import numpy as np

from vabench.tasks import common
from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task
from vabench.tasks.expert import ExpertContext
from vabench.tasks.objects import attach_object

X_RANGE, Y_RANGE = (0.20, 0.28), (-0.16, -0.04)


def sample_upright_bottle(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The bottle pose of grasp_single_bottle_upright (shared with place_single_bottle_upright)."""
    return sk.upright_bottle_pose(rng.uniform(*X_RANGE), rng.uniform(*Y_RANGE))


@dataclass(frozen=True)
class GraspSingleBottleUpright(Task):
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, "bottle_water.xml", "bottle")

    def sample(self, seed: int) -> Sample:
        return Sample({"bottle": sample_upright_bottle(self.rng(seed))})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        return common.grasp_evaluation(self, ix, s, latched, "bottle")

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from sk.side_grasp(ctx, "right", lambda v: v.pos("bottle"))
        yield from common.lift(ctx, "right", 0.10)


TASK = GraspSingleBottleUpright(
    name="grasp_single_bottle_upright",
    instruction="Pick up the upright bottle and lift it off the table.",
    arms=("right",),
    step_budget=50,
    checkpoints=common.GRASP_CHECKPOINTS,
    contact_pairs=(("bottle", "right_gripper"),),
)
