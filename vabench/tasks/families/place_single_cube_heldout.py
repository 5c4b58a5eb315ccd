"""place_single_cube_heldout: place_single_cube with a decoy pad and an obstacle in the way.

Controlled-transfer variant of place_single_cube (suite "transfer"; same instruction, arms,
budget and predicate; it reads the base family's summary). What is held out is the layout:
- a decoy pad, the goal pad's twin in blue (12 x 12 cm, 6 mm thick, `pad_blue.xml`), to the
  right of the green goal pad: centres 150-250 mm apart along x, far outside the 35 mm
  tolerance, so a cube on the decoy fails;
- an obstacle: a heavy purple wall (120 x 30 x 100 mm, 2.8 kg, `wall_purple.xml`) standing on
  the straight line from the cube to the goal pad, across it. Carrying the cube at the base
  expert's height (its bottom 60 mm above the pad) runs into the wall: it must be lifted over.

Scene (world m): the red 0.05 m cube (the base's) at x in [0.18, 0.26], y in [-0.16, -0.10]
(inside the base's ranges: the far part of its y range), yaw in [-45, 45] deg; the green goal
pad at x in [0.10, 0.14] (the base's), y in [0.09, 0.13] (90 mm further from the robot than the
base's [0, 0.04], to make room for the wall), the blue decoy at x in [0.29, 0.35], y in
[0.09, 0.13], both axis-aligned. The wall's centre lies on the segment from the cube's centre
to the goal pad's centre, midway between the point 85 mm from the cube (clear of the open
fingers around the cube) and the point 100 mm from the pad's centre (clear of the pad and of
the fingers over it); its long side is across the segment.
Drawn from the seed salted with `SALT`, so a seed gives another scene than the base's.
Success (the base's row, unchanged, on the goal pad): the cube was lifted >= 50 mm at some
point (latched); its x and y errors to the goal pad's centre each <= 35 mm; its height error to
its resting height on the pad <= 35 mm; the goal pad displaced <= 2 mm; cube-pad contact;
right gripper open. The decoy and the wall are not part of the predicate. Budget 100 steps.
Checkpoints: reached, grasped, lifted (latched), transported (x/y within tolerance), released
(gripper open), completed (as the base).
Expert: top-down grasp with GC 8 mm above the cube's centre (a grasp at the centre let the
cube slip out on MJX when lifted this high), lift the cube until its bottom clears the wall's top
by 30 mm, carry it over the goal pad at that height, lower it onto the pad, open, back off
upwards.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks.base import ObjectPoses, OnTable, Sample, Script, yaw_quat
from vabench.tasks.expert import ExpertContext
from vabench.tasks.families import place_single_cube as base
from vabench.tasks.families.grasp_single_cube import CUBE_HALF
from vabench.tasks.heldout import salted, variant

SALT = 0x6C5A2

CUBE_AT = dataclasses.replace(base.CUBE_AT, y=(-0.16, -0.10))
PAD_AT = dataclasses.replace(base.PAD_AT, y=(0.09, 0.13))
DECOY_AT = OnTable(x=(0.29, 0.35), y=(0.09, 0.13), half_h=base.PAD_HALF_THICK)
WALL_HALF = np.array([0.06, 0.015, 0.05])
CUBE_CLEAR = 0.085  # wall centre at least this far from the cube centre, along the segment
PAD_CLEAR = 0.10  # ... and at least this far from the goal pad's centre
OVER_WALL = 0.03  # the carried cube's bottom above the wall's top
GRASP_DZ = 0.008  # GC above the cube's centre when grasping (see the expert)


def wall_pose(cube: np.ndarray, pad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The wall across the cube-to-pad segment, midway between its two clearance points."""
    d = pad[:2] - cube[:2]
    length = np.linalg.norm(d)
    u = d / length
    along = CUBE_CLEAR + 0.5 * (length - CUBE_CLEAR - PAD_CLEAR)
    xy = cube[:2] + along * u
    yaw = np.arctan2(u[1], u[0]) + np.pi / 2  # body x (the long side) across the segment
    return np.r_[xy, rc.TABLE_Z + WALL_HALF[2]], yaw_quat(yaw)


@dataclass(frozen=True)
class PlaceSingleCubeHeldout(base.PlaceSingleCube):
    """The base family's predicate (inherited), plus the decoy and the wall, and the expert
    that carries the cube over the wall."""

    def draw(self, rng: np.random.Generator) -> ObjectPoses:
        poses = super().draw(rng)  # the red cube, the green goal pad, the decoy
        return {**poses, "obstacle": wall_pose(poses["cube"][0], poses["pad"][0])}

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from common.topdown_grasp(ctx, "right", "cube", grasp_dz=GRASP_DZ)
        wall_top = ctx.view.pos("obstacle")[2] + WALL_HALF[2]
        pad = ctx.view.pos("pad")
        rest_z = pad[2] + base.PAD_HALF_THICK + CUBE_HALF
        carry_z = wall_top + OVER_WALL + CUBE_HALF  # the cube centre's height over the wall
        yield from common.carry_and_release(
            ctx, "right", "cube", pad[:2], rest_z, clearance=carry_z - rest_z
        )


TASK = variant(
    base.TASK,
    "place_single_cube_heldout",
    PlaceSingleCubeHeldout,
    objects=(*base.TASK.objects, ("decoy", "pad_blue.xml"), ("obstacle", "wall_purple.xml")),
    on_table=(("cube", CUBE_AT), ("pad", PAD_AT), ("decoy", DECOY_AT)),
    seed_stream=salted(SALT),
)
