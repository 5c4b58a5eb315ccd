"""place_single_bottle_upright: put the upright bottle on the green pad, right arm.

Scene (paper Table tab:seed-spec-place): the bottle as in grasp_single_bottle_upright
(bottle_water.xml, upright, x in [0.20, 0.28], y in [-0.16, -0.04]); a green pad (half-size
0.065 m, FACTS; 3 mm half-thick) at x in [0.03, 0.09], y in [0.07, 0.13], axis-aligned.
Success (all now, plus one latch; place_single_cube's shared predicate): the bottle was lifted
>= 50 mm at some point (latched); the x and y errors of its body centre to the pad centre each
<= 40 mm; its height error to the resting height on the pad (pad half-thickness + 60 mm) <= 35
mm; the pad displaced <= 2 mm; bottle-pad contact; right gripper open. Budget 100 steps.
The paper's row checks no orientation: a bottle lying on the pad has its centre 31 mm above the
pad's top, 29 mm below the upright resting height, and passes the height check.
Checkpoints: reached, grasped, lifted (latched), transported (x/y and height within
tolerance), released (gripper open), completed.
Expert: side grasp as in grasp_single_bottle_upright, lift 60 mm, carry over the pad centre,
lower to 4 mm above resting, open, back off upwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task, yaw_quat
from vabench.tasks.expert import ExpertContext
from vabench.tasks.grasp_single_bottle_upright import sample_upright_bottle
from vabench.tasks.objects import attach_object
from vabench.tasks.place_single_cube import place_checks

PAD_HALF_THICK = 0.003
XY_TOL = 0.040
HEIGHT_TOL = 0.035
PAD_MOVE_TOL = 0.002
PAD_X, PAD_Y = (0.03, 0.09), (0.07, 0.13)
REST_HEIGHT = PAD_HALF_THICK + sk.BOTTLE_HALF_H  # bottle origin above the pad centre


@dataclass(frozen=True)
class PlaceSingleBottleUpright(Task):
    bottle_file: str = "bottle_water.xml"
    rest_height: float = REST_HEIGHT
    """The bottle's origin above the pad centre when it stands on the pad (the held-out
    variant's container is taller)."""

    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, self.bottle_file, "bottle")
        attach_object(spec, "pad_green_130.xml", "pad")

    def sample_bottle(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        return sample_upright_bottle(rng)

    def sample(self, seed: int) -> Sample:
        rng = self.rng(seed)
        bottle = self.sample_bottle(rng)
        pad = np.array([rng.uniform(*PAD_X), rng.uniform(*PAD_Y), rc.TABLE_Z + PAD_HALF_THICK])
        return Sample({"bottle": bottle, "pad": (pad, yaw_quat(0.0))})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        return place_checks(
            self,
            ix,
            s,
            latched,
            "bottle",
            "pad",
            self.rest_height,
            XY_TOL,
            HEIGHT_TOL,
            PAD_MOVE_TOL,
        )

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from sk.side_grasp(ctx, "right", lambda v: v.pos("bottle"))
        yield from common.lift(ctx, "right", 0.06)
        pad = ctx.view.pos("pad")
        target_z = pad[2] + self.rest_height
        yield from common.carry_and_release(ctx, "right", "bottle", pad[:2], target_z)


TASK = PlaceSingleBottleUpright(
    name="place_single_bottle_upright",
    instruction="Pick up the bottle and place it upright on the green pad.",
    arms=("right",),
    step_budget=100,
    checkpoints=common.PLACE_CHECKPOINTS,
    latches=("was_lifted",),
    contact_pairs=(("bottle", "right_gripper"), ("bottle", "pad")),
)
