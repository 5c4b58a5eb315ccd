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
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from vabench.tasks.base import OnTable
from vabench.tasks.families import place_cube_on_cube as base
from vabench.tasks.heldout import salted, variant

SALT = 0x6C5A4

RED_HALF = base.HALF  # 25 mm
SUPPORT_HALF = np.array([0.04, 0.03, 0.03])
SUPPORT_AT = OnTable(x=(0.08, 0.12), y=(0.03, 0.07), half_h=0.03, yaw_deg=(50.0, 130.0))


@dataclass(frozen=True)
class PlaceCubeOnCubeHeldout(base.PlaceCubeOnCube):
    """The base family with the block's top face and resting height (the scaling rule)."""

    def top_face(self) -> jax.Array:
        return jnp.asarray(SUPPORT_HALF[:2])

    def resting_z(self, base_z: Any) -> Any:
        return base_z + SUPPORT_HALF[2] + RED_HALF


TASK = variant(
    base.TASK,
    "place_cube_on_cube_heldout",
    PlaceCubeOnCubeHeldout,
    objects=(("red", "cube_red_50.xml"), ("base", "block_green_80x60x60.xml")),
    on_table=(("red", base.RED_AT), ("base", SUPPORT_AT)),
    seed_stream=salted(SALT),
)
