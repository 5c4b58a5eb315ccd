"""grasp_single_bottle_upright_heldout: the held-out container of grasp_single_bottle_upright
(transfer track).

What is held out: the container. Instead of the base's round water bottle (bottle_water.xml:
64 mm across, 168 mm tall, body 120 mm; blue, yellow label, red cap) a tall square-section
bottle stands upright (bottle_square.xml: 50 x 50 mm section with 8 mm rounded edges, body
180 mm, 220 mm overall; orange, purple label, white cap). Its origin, the centre of the body,
is 90 mm above the table (the base's: 60 mm).
Scene: the base's ranges, drawn from the variant's own seed stream (`heldout_rng`): x in
[0.20, 0.28], y in [-0.16, -0.04], fixed upright orientation with the faces normal to world x
and y (no yaw, as in the base).
Success (the base's predicate, unchanged): the bottle lifted more than 50 mm above its settled
height and the right gripper closed (both now, not latched). Instruction, arm and budget (50
steps) are the base's.
Checkpoints: reached (GC within 30 mm of the body's centre), grasped (closed and touching),
lifted (> 50 mm), completed (success).
Expert: the base's side grasp (approach along +y, fingers closing along world x on two flat
faces, at the body's centre), close, lift 100 mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import mujoco
import numpy as np

from vabench.tasks import common
from vabench.tasks import skills_heldout_bottles as hb
from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task
from vabench.tasks.expert import ExpertContext
from vabench.tasks.grasp_single_bottle_upright import TASK as BASE
from vabench.tasks.objects import attach_object

X_RANGE, Y_RANGE = (0.20, 0.28), (-0.16, -0.04)


def sample_upright_square(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The container pose (shared with place_single_bottle_upright_heldout)."""
    return hb.upright_square_pose(rng.uniform(*X_RANGE), rng.uniform(*Y_RANGE))


@dataclass(frozen=True)
class GraspSingleBottleUprightHeldout(Task):
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, "bottle_square.xml", "bottle")

    @staticmethod
    def rng(seed: int) -> np.random.Generator:
        return hb.heldout_rng(seed)

    def sample(self, seed: int) -> Sample:
        return Sample({"bottle": sample_upright_square(self.rng(seed))})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        return common.grasp_evaluation(self, ix, s, latched, "bottle")

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from sk.side_grasp(ctx, "right", lambda v: v.pos("bottle"))
        yield from common.lift(ctx, "right", 0.10)


TASK = GraspSingleBottleUprightHeldout(
    name="grasp_single_bottle_upright_heldout",
    instruction=BASE.instruction,
    arms=BASE.arms,
    step_budget=BASE.step_budget,
    checkpoints=common.GRASP_CHECKPOINTS,
    contact_pairs=(("bottle", "right_gripper"),),
    suite="transfer",
    base_family=BASE.name,
)
