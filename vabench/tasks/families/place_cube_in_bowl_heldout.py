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
import numpy as np

from vabench.tasks.base import ObjectIndex, OnTable, SlotState
from vabench.tasks.families import place_cube_in_bowl as base
from vabench.tasks.heldout import salted, variant

SALT = 0x6C5A3

BASIN_AT = OnTable(x=(0.04, 0.08), y=(0.08, 0.12), yaw_deg=(-20.0, 20.0))
BASIN_FLOOR = 0.008
BASIN_RIM = 0.06
INTERIOR_HALF = np.array([0.09, 0.07])  # interior half-extents along body x and y

RIM_CLEARANCE = 0.045  # carried cube's bottom above the rim
RELEASE_DROP = 0.01  # cube bottom above the floor when the fingers open


def interior_offset(p_cube: jax.Array, p_basin: jax.Array, r_basin: jax.Array) -> jax.Array:
    """The cube centre's horizontal offset from the basin's origin along its body x and y."""
    return r_basin[:, :2].T @ (p_cube - p_basin)


@dataclass(frozen=True)
class PlaceCubeInBowlHeldout(base.PlaceCubeInBowl):
    """The base family with the basin's interior as "centred" and its own carry heights."""

    def centred(self, ix: ObjectIndex, s: SlotState, p: jax.Array, b: jax.Array) -> jax.Array:
        uv = interior_offset(p, b, ix.mat(s.qpos, "bowl"))
        return jnp.all(jnp.abs(uv) < INTERIOR_HALF)

    def carry_heights(self, bowl_z: float) -> tuple[float, float]:
        high = bowl_z + BASIN_RIM + RIM_CLEARANCE + base.CUBE_HALF
        return high, bowl_z + BASIN_FLOOR + RELEASE_DROP + base.CUBE_HALF


TASK = variant(
    base.TASK,
    "place_cube_in_bowl_heldout",
    PlaceCubeInBowlHeldout,
    objects=(("cube", "cube_red_40.xml"), ("bowl", "basin_navy.xml")),
    on_table=(("cube", base.CUBE_AT), ("bowl", BASIN_AT)),
    seed_stream=salted(SALT),
)
