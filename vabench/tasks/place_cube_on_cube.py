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
from vabench.tasks.expert import ExpertContext, yaw_of
from vabench.tasks.objects import attach_object

HALF = 0.025  # both cubes
RED_X, RED_Y = (0.20, 0.26), (-0.14, -0.06)
BASE_X, BASE_Y = (0.10, 0.14), (0.0, 0.04)
YAW_DEG = (-45.0, 45.0)

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
class PlaceCubeOnCube(Task):
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, "cube_red_50.xml", "red")
        attach_object(spec, "cube_green_50.xml", "base")

    def sample(self, seed: int) -> Sample:
        rng = self.rng(seed)
        red = np.array([rng.uniform(*RED_X), rng.uniform(*RED_Y), rc.TABLE_Z + HALF])
        red_yaw = np.radians(rng.uniform(*YAW_DEG))
        base = np.array([rng.uniform(*BASE_X), rng.uniform(*BASE_Y), rc.TABLE_Z + HALF])
        base_yaw = np.radians(rng.uniform(*YAW_DEG))
        return Sample({"red": (red, yaw_quat(red_yaw)), "base": (base, yaw_quat(base_yaw))})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        p, b = ix.pos(s.qpos, "red"), ix.pos(s.qpos, "base")
        overlap = top_overlap(p, ix.mat(s.qpos, "red"), b, ix.mat(s.qpos, "base"))
        placement = {
            "overlap": jnp.all(overlap >= OVERLAP_MIN),
            "height": jnp.abs(p[2] - (b[2] + 2 * HALF)) <= HEIGHT_TOL,
        }
        still = ix.displacement(s, "base") <= BASE_MOVE_TOL
        return common.place_evaluation(
            self, ix, s, latched, "red", "base", placement, ("base_still", still)
        )

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from common.topdown_grasp(ctx, "right", "red")
        yield from common.lift(ctx, "right", 0.08)
        turn = yaw_of(ctx.view.mat("base")) - yaw_of(ctx.view.mat("red"))
        turn = (turn + np.pi / 4) % (np.pi / 2) - np.pi / 4  # cube symmetry: 90 deg
        c, s = np.cos(turn), np.sin(turn)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        yield from ctx.rotate_to("right", rz @ ctx.view.arms["right"].rot)
        base = ctx.view.pos("base")
        yield from common.carry_and_release(ctx, "right", "red", base[:2], base[2] + 2 * HALF)


TASK = PlaceCubeOnCube(
    name="place_cube_on_cube",
    instruction="Pick up the red cube and stack it on top of the green cube.",
    arms=("right",),
    step_budget=200,
    checkpoints=common.PLACE_CHECKPOINTS,
    latches=("was_lifted",),
    contact_pairs=(("red", "right_gripper"), ("red", "base")),
)
