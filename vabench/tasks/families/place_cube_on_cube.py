"""place_cube_on_cube: stack the red cube on the green cube, right arm.

Scene (paper Table tab:seed-spec-place): a red 0.05 m cube at x in [0.20, 0.26],
y in [-0.14, -0.06] and a green 0.05 m base cube at x in [0.10, 0.14], y in [0, 0.04], both
resting on the table. The paper's "yaw in [-45, 45] deg" is drawn for both cubes, independently:
FACTS names it for the base (the base's yaw is what makes the stacking need an alignment), and
the red cube's yaw is drawn as in grasp_single_cube, whose red cube this is.
Success (all now, plus one latch), as the paper's row:
- was_lifted: the red cube was lifted >= 50 mm above its settled height at some point (latched);
- overlap: top-surface overlap >= 2 mm. Precisely: for each of the base's two horizontal axes u
  (its body x and y), the interval covered by the red cube projected onto u (centre
  u . (p_red - p_base), half-extent 25 mm * sum_j |u . R_red e_j|, exact for any red pose)
  overlaps the base's top face [-25, 25] mm along u by at least 2 mm. Both axes must hold, so the
  red cube's footprint reaches at least 2 mm onto the top face in each direction;
- height: |z_red - (z_base + 50 mm)| <= 12 mm (the red cube resting on the base sits at 0);
- base_still: the base displaced <= 12 mm from its settled position;
- contact: red-base contact;
- gripper_open: the right gripper open.
Budget 200 steps.
Checkpoints: reached (GC within 30 mm of the red cube), grasped (closed and touching), lifted
(latched), transported (overlap and height), released (gripper open with overlap), completed.
Expert: top-down grasp across the red cube's faces, lift, turn the held cube about the vertical
to the base's yaw (modulo 90 deg), carry it over the base, lower to 4 mm above resting on it,
open, back off upwards.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from vabench.tasks import common
from vabench.tasks.base import ObjectIndex, OnTable, Sample, Script, SlotState
from vabench.tasks.expert import ExpertContext, yaw_of
from vabench.tasks.grasp_place import Check, PlaceFamily

HALF = 0.025  # both cubes
YAW_DEG = (-45.0, 45.0)
RED_AT = OnTable(x=(0.20, 0.26), y=(-0.14, -0.06), half_h=HALF, yaw_deg=YAW_DEG)
BASE_AT = OnTable(x=(0.10, 0.14), y=(0.0, 0.04), half_h=HALF, yaw_deg=YAW_DEG)

OVERLAP_MIN = 0.002
HEIGHT_TOL = 0.012
BASE_MOVE_TOL = 0.012


def top_overlap(
    p_red: jax.Array,
    r_red: jax.Array,
    p_base: jax.Array,
    r_base: jax.Array,
    face: Any = HALF,
    red_half: float = HALF,
):
    """Overlap depth (m) of the red cube's projection with the base's top face along each of the
    base's horizontal axes, shape (2,). `face`: the top face's half extents along the base's x
    and y (a scalar for a cube; the held-out variant's block passes its own)."""
    axes = r_base[:, :2].T  # (2, 3): base x and y in world
    centre = axes @ (p_red - p_base)
    half_extent = red_half * jnp.sum(jnp.abs(axes @ r_red), axis=1)
    return jnp.minimum(centre + half_extent, face) - jnp.maximum(centre - half_extent, -face)


@dataclass(frozen=True)
class PlaceCubeOnCube(PlaceFamily):
    """The family; its held-out variant's support has its own top face and resting height."""

    def top_face(self) -> Any:
        """The support's top face: half extents along its body x and y."""
        return HALF

    def resting_z(self, base_z: Any) -> Any:
        """The red cube's centre height when it rests on a support whose centre is at base_z."""
        return base_z + 2 * HALF

    def placement(self, ix: ObjectIndex, s: SlotState) -> tuple[dict[str, jax.Array], Check]:
        p, b = ix.pos(s.qpos, "red"), ix.pos(s.qpos, "base")
        r_red, r_base = ix.mat(s.qpos, "red"), ix.mat(s.qpos, "base")
        overlap = top_overlap(p, r_red, b, r_base, face=self.top_face(), red_half=HALF)
        placement = {
            "overlap": jnp.all(overlap >= OVERLAP_MIN),
            "height": jnp.abs(p[2] - self.resting_z(b[2])) <= HEIGHT_TOL,
        }
        still = ix.displacement(s, "base") <= BASE_MOVE_TOL
        return placement, ("base_still", still)

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from common.topdown_grasp(ctx, "right", "red")
        yield from common.lift(ctx, "right", 0.08)
        turn = yaw_of(ctx.view.mat("base")) - yaw_of(ctx.view.mat("red"))
        turn = (turn + np.pi / 4) % (np.pi / 2) - np.pi / 4  # red cube symmetry: 90 deg
        c, s = np.cos(turn), np.sin(turn)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        yield from ctx.rotate_to("right", rz @ ctx.view.arms["right"].rot)
        base = ctx.view.pos("base")
        yield from common.carry_and_release(ctx, "right", "red", base[:2], self.resting_z(base[2]))


TASK = PlaceCubeOnCube(
    name="place_cube_on_cube",
    instruction="Pick up the red cube and stack it on top of the green cube.",
    step_budget=200,
    objects=(("red", "cube_red_50.xml"), ("base", "cube_green_50.xml")),
    on_table=(("red", RED_AT), ("base", BASE_AT)),
)
