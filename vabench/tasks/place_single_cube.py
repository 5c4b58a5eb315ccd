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

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks.base import (
    Evaluation,
    ObjectIndex,
    Sample,
    Script,
    SlotState,
    Task,
    yaw_quat,
)
from vabench.tasks.expert import ExpertContext
from vabench.tasks.grasp_single_cube import CUBE_HALF, sample_cube
from vabench.tasks.objects import attach_object

PAD_HALF_THICK = 0.003
XY_TOL = 0.035
HEIGHT_TOL = 0.035
PAD_MOVE_TOL = 0.002
PAD_X, PAD_Y = (0.10, 0.14), (0.0, 0.04)


def place_checks(
    task: Task,
    ix: ObjectIndex,
    s: SlotState,
    latched: jax.Array,
    obj: str,
    target: str,
    rest_height: float,
    xy_tol: float,
    height_tol: float,
    target_move_tol: float,
) -> Evaluation:
    """The pad-placement predicate (paper: _single_right_arm_place_target_task): x and y
    errors each within xy_tol, height error within height_tol of the resting height, target
    displaced at most target_move_tol; the rest is `common.place_evaluation`."""
    p, t = ix.pos(s.qpos, obj), ix.pos(s.qpos, target)
    placement = {
        "xy_within_tolerance": jnp.all(jnp.abs(p[:2] - t[:2]) <= xy_tol),
        "height_within_tolerance": jnp.abs(p[2] - (t[2] + rest_height)) <= height_tol,
    }
    still = ix.displacement(s, target) <= target_move_tol
    return common.place_evaluation(
        task, ix, s, latched, obj, target, placement, ("target_not_displaced", still)
    )


@dataclass(frozen=True)
class PlaceSingleCube(Task):
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, "cube_red_50.xml", "cube")
        attach_object(spec, "pad_green.xml", "pad")

    def sample(self, seed: int) -> Sample:
        rng = self.rng(seed)
        cube = sample_cube(rng)
        pad = np.array([rng.uniform(*PAD_X), rng.uniform(*PAD_Y), rc.TABLE_Z + PAD_HALF_THICK])
        return Sample({"cube": cube, "pad": (pad, yaw_quat(0.0))})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        return place_checks(
            self,
            ix,
            s,
            latched,
            "cube",
            "pad",
            PAD_HALF_THICK + CUBE_HALF,
            XY_TOL,
            HEIGHT_TOL,
            PAD_MOVE_TOL,
        )

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
    arms=("right",),
    step_budget=100,
    checkpoints=common.PLACE_CHECKPOINTS,
    latches=("was_lifted",),
    contact_pairs=(("cube", "right_gripper"), ("cube", "pad")),
)
