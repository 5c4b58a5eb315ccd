"""place_cube_on_cube_heldout: stack the red cube on a rotated, unequal green support.

Controlled-transfer variant of place_cube_on_cube (suite "transfer"; same instruction, arms and
budget; it reads the base family's summary). What is held out is the support:
- unequal: instead of the base's green 5 cm cube, a green block of 80 x 60 x 60 mm (body x, y,
  z; 0.2 kg, `block_green_80x60x60.xml`), larger than the red cube and 10 mm taller than the
  base cube, with a rectangular top face;
- rotated: its yaw is drawn in [50, 130] deg, outside the base's [-45, 45]. For the base's cube
  (symmetric every 90 deg) every yaw is one of [-45, 45]; the block is symmetric only every
  180 deg, so this range puts its long side within 40 deg of the world y axis, never within
  45 deg of x, as no base seed can.

Scene (world m): the red 0.05 m cube as in the base (x in [0.20, 0.26], y in [-0.14, -0.06],
yaw in [-45, 45] deg); the support resting on the table at x in [0.08, 0.12], y in [0.03, 0.07]
(30 mm further from the red cube than the base's range, so the larger block stays clear of the
open fingers around the red cube), yaw as above. Drawn from the seed salted with `SALT`, so a
seed gives another scene than the base's.
Success (all now, plus one latch), the base's row with the support's own dimensions:
- was_lifted: the red cube was lifted >= 50 mm above its settled height at some point (latched);
- overlap: top-surface overlap >= 2 mm: for each of the support's horizontal body axes u, the
  red cube's projection onto u (exact for any red pose) overlaps the support's top face,
  [-40, 40] mm along x and [-30, 30] mm along y, by at least 2 mm. The scaling rule: the face
  extents are the support's own half-sizes (the base uses its cube's 25 mm on both axes); the
  2 mm threshold is a minimum contact footprint, an absolute length, so it is not scaled;
- height: |z_red - (z_support + 30 mm + 25 mm)| <= 12 mm (the support's half-height plus the
  red cube's: 0 when the red cube rests on it; the 12 mm tolerance is absolute, not scaled);
- base_still: the support displaced <= 12 mm from its settled position (the base's);
- contact: red-support contact;
- gripper_open: the right gripper open.
Budget 200 steps.
Checkpoints: reached, grasped, lifted (latched), transported (overlap and height), released
(gripper open with overlap), completed (as the base).
Expert: the base's method: top-down grasp across the red cube's faces, lift, turn the held cube
about the vertical to the support's yaw (modulo 90 deg, the red cube's symmetry), carry it over
the support's centre, lower it onto the top face, open, back off upwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks import place_cube_on_cube as base
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task, yaw_quat
from vabench.tasks.expert import ExpertContext, yaw_of
from vabench.tasks.grasp_single_cube_heldout import salted_rng
from vabench.tasks.objects import attach_object

SALT = 0x6C5A4

RED_HALF = base.HALF  # 25 mm
RED_X, RED_Y, RED_YAW_DEG = base.RED_X, base.RED_Y, base.YAW_DEG
SUPPORT_HALF = np.array([0.04, 0.03, 0.03])
SUPPORT_X, SUPPORT_Y, SUPPORT_YAW_DEG = (0.08, 0.12), (0.03, 0.07), (50.0, 130.0)

OVERLAP_MIN = base.OVERLAP_MIN  # 2 mm
HEIGHT_TOL = base.HEIGHT_TOL  # 12 mm
BASE_MOVE_TOL = base.BASE_MOVE_TOL  # 12 mm


def top_overlap(
    p_red: jax.Array, r_red: jax.Array, p_sup: jax.Array, r_sup: jax.Array
) -> jax.Array:
    """Overlap depth (m) of the red cube's projection with the support's top face along each of
    the support's horizontal axes, shape (2,): the base's rule with the support's extents."""
    face = jnp.asarray(SUPPORT_HALF[:2])
    return base.top_overlap(p_red, r_red, p_sup, r_sup, face=face, red_half=RED_HALF)


@dataclass(frozen=True)
class PlaceCubeOnCubeHeldout(Task):
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, "cube_red_50.xml", "red")
        attach_object(spec, "block_green_80x60x60.xml", "base")

    def sample(self, seed: int) -> Sample:
        rng = salted_rng(seed, SALT)
        red = np.array([rng.uniform(*RED_X), rng.uniform(*RED_Y), rc.TABLE_Z + RED_HALF])
        red_yaw = np.radians(rng.uniform(*RED_YAW_DEG))
        sup = np.array(
            [rng.uniform(*SUPPORT_X), rng.uniform(*SUPPORT_Y), rc.TABLE_Z + SUPPORT_HALF[2]]
        )
        sup_yaw = np.radians(rng.uniform(*SUPPORT_YAW_DEG))
        return Sample({"red": (red, yaw_quat(red_yaw)), "base": (sup, yaw_quat(sup_yaw))})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        p, b = ix.pos(s.qpos, "red"), ix.pos(s.qpos, "base")
        overlap = top_overlap(p, ix.mat(s.qpos, "red"), b, ix.mat(s.qpos, "base"))
        placement = {
            "overlap": jnp.all(overlap >= OVERLAP_MIN),
            "height": jnp.abs(p[2] - (b[2] + SUPPORT_HALF[2] + RED_HALF)) <= HEIGHT_TOL,
        }
        still = ix.displacement(s, "base") <= BASE_MOVE_TOL
        return common.place_evaluation(
            self, ix, s, latched, "red", "base", placement, ("base_still", still)
        )

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from common.topdown_grasp(ctx, "right", "red")
        yield from common.lift(ctx, "right", 0.08)
        turn = yaw_of(ctx.view.mat("base")) - yaw_of(ctx.view.mat("red"))
        turn = (turn + np.pi / 4) % (np.pi / 2) - np.pi / 4  # red cube symmetry: 90 deg
        c, s = np.cos(turn), np.sin(turn)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        yield from ctx.rotate_to("right", rz @ ctx.view.arms["right"].rot)
        sup = ctx.view.pos("base")
        yield from common.carry_and_release(
            ctx, "right", "red", sup[:2], sup[2] + SUPPORT_HALF[2] + RED_HALF
        )


TASK = PlaceCubeOnCubeHeldout(
    name="place_cube_on_cube_heldout",
    instruction=base.TASK.instruction,
    arms=base.TASK.arms,
    step_budget=base.TASK.step_budget,
    checkpoints=base.TASK.checkpoints,
    latches=base.TASK.latches,
    contact_pairs=base.TASK.contact_pairs,
    suite="transfer",
    base_family=base.TASK.name,
)
