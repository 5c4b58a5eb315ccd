"""place_cube_in_bowl_heldout: place_cube_in_bowl with a larger container of another shape.

Controlled-transfer variant of place_cube_in_bowl (suite "transfer"; same instruction, arms and
budget; it reads the base family's summary). What is held out is the container: instead of the
round bowl (16-gon floor of radius 46 mm, walls tilted 35 deg outwards, rim radius ~72 mm, 52 mm
high, mid blue) a rectangular navy-blue basin (`basin_navy.xml`): interior 180 x 140 mm at the
floor and at every height (vertical walls), walls 60 mm high, floor 8 mm thick (the bowl's),
outside 196 x 156 mm, 0.9 kg. It stays blue (a darker navy, not the bowl's glaze) because the
instruction the variant keeps names "the blue bowl".

Scene (world m): the red 0.04 m cube as in the base (x in [0.22, 0.27], y in [-0.17, -0.10],
yaw in [-45, 45] deg); the basin upright at x in [0.04, 0.08], y in [0.08, 0.12] (moved 60-80 mm
away from the base's bowl range so that the larger basin stays clear of the fingers around the
cube), yaw in [-20, 20] deg (the round bowl has none). Its origin is the centre of its bottom,
on the table. Drawn from the seed salted with `SALT`, so a seed gives another scene than the
base's.
Success (all now, plus one latch), the base's row adapted to the basin's interior:
- was_lifted: the cube was lifted >= 50 mm above its settled height at some point (latched);
- centred: the cube centre inside the basin's interior footprint, |u| < 90 mm and |v| < 70 mm
  along the basin's body x and y axes. The rule behind both: the base's 55 mm radius is the
  round bowl's interior radius at the height of a resting cube's centre (28 mm above its bottom:
  40 + 20 tan 35 deg ~ 54 mm); the basin's interior at that height is its floor footprint;
- height: cube centre height minus basin origin height in [15, 95] mm (the base's band: the
  floor is the bowl's 8 mm, so a cube resting on it sits at 28 mm in both);
- bowl_still: the basin displaced < 5 mm from its settled position (the base's);
- contact: cube-basin contact;
- gripper_open: the right gripper open.
Budget 50 steps.
Checkpoints: reached, grasped, lifted (latched), transported (centred and height), released
(gripper open while centred), completed (as the base).
Expert: the base's method: top-down grasp across the cube's faces with GC 5 mm above its
centre, lift, carry open-loop (grasp offset measured after the lift) over the basin's centre
with the cube's bottom 45 mm above the rim, lower it until its bottom is 10 mm above the floor,
open, back off upwards; a cube that slipped out on the way is not pressed on.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks import place_cube_in_bowl as base
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task, yaw_quat
from vabench.tasks.expert import ExpertContext
from vabench.tasks.grasp_single_cube_heldout import salted_rng
from vabench.tasks.objects import attach_object

SALT = 0x6C5A3

CUBE_HALF = base.CUBE_HALF
CUBE_X, CUBE_Y, CUBE_YAW_DEG = base.CUBE_X, base.CUBE_Y, base.CUBE_YAW_DEG
BASIN_X, BASIN_Y, BASIN_YAW_DEG = (0.04, 0.08), (0.08, 0.12), (-20.0, 20.0)
BASIN_FLOOR = 0.008
BASIN_RIM = 0.06
INTERIOR_HALF = np.array([0.09, 0.07])  # interior half-extents along body x and y

REL_HEIGHT = base.REL_HEIGHT  # 15-95 mm
BOWL_MOVE_TOL = base.BOWL_MOVE_TOL  # 5 mm

RIM_CLEARANCE = 0.045  # carried cube's bottom above the rim
RELEASE_DROP = 0.01  # cube bottom above the floor when the fingers open
GRASP_DZ = base.GRASP_DZ


def interior_offset(p_cube: jax.Array, p_basin: jax.Array, r_basin: jax.Array) -> jax.Array:
    """The cube centre's horizontal offset from the basin's origin along its body x and y."""
    return r_basin[:, :2].T @ (p_cube - p_basin)


@dataclass(frozen=True)
class PlaceCubeInBowlHeldout(Task):
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, "cube_red_40.xml", "cube")
        attach_object(spec, "basin_navy.xml", "bowl")

    def sample(self, seed: int) -> Sample:
        rng = salted_rng(seed, SALT)
        cube = np.array([rng.uniform(*CUBE_X), rng.uniform(*CUBE_Y), rc.TABLE_Z + CUBE_HALF])
        cube_yaw = np.radians(rng.uniform(*CUBE_YAW_DEG))
        basin = np.array([rng.uniform(*BASIN_X), rng.uniform(*BASIN_Y), rc.TABLE_Z])
        basin_yaw = np.radians(rng.uniform(*BASIN_YAW_DEG))
        return Sample({"cube": (cube, yaw_quat(cube_yaw)), "bowl": (basin, yaw_quat(basin_yaw))})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        p, b = ix.pos(s.qpos, "cube"), ix.pos(s.qpos, "bowl")
        uv = interior_offset(p, b, ix.mat(s.qpos, "bowl"))
        rel = p[2] - b[2]
        placement = {
            "centred": jnp.all(jnp.abs(uv) < INTERIOR_HALF),
            "height": (rel >= REL_HEIGHT[0]) & (rel <= REL_HEIGHT[1]),
        }
        still = ix.displacement(s, "bowl") < BOWL_MOVE_TOL
        return common.place_evaluation(
            self, ix, s, latched, "cube", "bowl", placement, ("bowl_still", still)
        )

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from common.topdown_grasp(ctx, "right", "cube", grasp_dz=GRASP_DZ)
        yield from common.lift(ctx, "right", 0.07)
        offset = ctx.view.arms["right"].gc - ctx.view.pos("cube")
        basin = ctx.view.pos("bowl")
        high = np.r_[basin[:2], basin[2] + BASIN_RIM + RIM_CLEARANCE + CUBE_HALF] + offset
        low = np.r_[basin[:2], basin[2] + BASIN_FLOOR + RELEASE_DROP + CUBE_HALF] + offset
        yield from ctx.move_to("right", np.r_[ctx.view.arms["right"].gc[:2], high[2]], order="z")
        yield from ctx.move_to("right", high, order="xyz")
        held = np.linalg.norm(ctx.view.arms["right"].gc - offset - ctx.view.pos("cube")) < 0.015
        if held:  # else it has slipped out on the way: lowering would press on it; just open
            yield from ctx.move_to("right", low, order="z")
        yield from ctx.grip("right", close=False)
        yield from common.lift(ctx, "right", 0.05)


TASK = PlaceCubeInBowlHeldout(
    name="place_cube_in_bowl_heldout",
    instruction=base.TASK.instruction,
    arms=base.TASK.arms,
    step_budget=base.TASK.step_budget,
    checkpoints=base.TASK.checkpoints,
    latches=base.TASK.latches,
    contact_pairs=base.TASK.contact_pairs,
    suite="transfer",
    base_family=base.TASK.name,
)
