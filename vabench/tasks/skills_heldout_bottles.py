"""Held-out containers, their poses and the seed stream shared by the bottle transfer variants
(grasp_single_bottle_heldout, grasp_single_bottle_upright_heldout,
place_single_bottle_upright_heldout). No TASK here: not a family, so not in `families/`.

Objects (assets/objects/):
- bottle_shampoo.xml: a flat shampoo bottle with a pump, rounded-rectangle section 56 x 38 mm,
  body 160 mm, 205 mm overall; origin at the centre of the body, axis = local z (pump at +z),
  width = local x, thickness = local y. Magenta, white label, black pump.
- bottle_square.xml: a tall square-section bottle with a flip cap, 50 x 50 mm, body 180 mm,
  220 mm overall; origin at the centre of the body, axis = local z. Orange, purple label, white
  cap.
The base families' water bottle (bottle_water.xml) is round, 64 mm across, 168 mm tall.

Seeds: a variant draws its scene from its own stream, `heldout_rng(seed)` (the seed mixed with
HELDOUT_STREAM), so seed s of a variant is not seed s of its base with another object.
"""

from __future__ import annotations

import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks.base import quat_mul, yaw_quat

SHAMPOO_HALF_W = 0.028  # half the width (local x)
SHAMPOO_HALF_T = 0.019  # half the thickness (local y): centre height when lying
SHAMPOO_HALF_L = 0.080  # half the body length (local z)
SHAMPOO_LENGTH = 0.205  # bottom to the top of the pump
SQUARE_HALF_W = 0.025  # half the side of the square section
SQUARE_HALF_H = 0.090  # half the body height: origin above the bottom face
SQUARE_HEIGHT = 0.220  # bottom to the top of the cap

HELDOUT_STREAM = 10  # mixed into every variant seed: held-out seeds are their own stream

# Lying shampoo at yaw 0: axis (local z) along world +x, thickness (local y) up, so the width
# (local x) runs along world +y. Columns are the images of the local axes.
_LYING = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def heldout_rng(seed: int) -> np.random.Generator:
    """The variants' seed stream: deterministic in the seed, independent of the base's."""
    return np.random.default_rng([HELDOUT_STREAM, seed])


def mat_to_quat(r: np.ndarray) -> np.ndarray:
    """wxyz quaternion of a rotation matrix."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.asarray(r, float).ravel())
    return quat


def lying_shampoo_pose(x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """The shampoo bottle on a broad face; yaw 0 = axis along world +x (pump to the right)."""
    quat = quat_mul(yaw_quat(yaw), mat_to_quat(_LYING))
    return np.array([x, y, rc.TABLE_Z + SHAMPOO_HALF_T]), quat
