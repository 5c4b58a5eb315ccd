"""probe_cube: one free 5 cm cube on the table, for probing grasps through the simulator core.

Randomization (the grasp_single_cube range of the paper's Table tab:seed-spec-grasp):
x in [0.18, 0.26], y in [-0.16, -0.06], yaw in [-45, 45] deg, resting on the table.
Success: the cube lifted more than 50 mm above its initial height with the right gripper closed
(not latched here; the task suite adds latching).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx.scene import add_free_box
from vabench.tasks.base import ObjectPoses, Task, yaw_quat

CUBE_HALF = 0.025
CUBE_MASS = 0.08  # kg: a 5 cm block of dense wood
LIFT_M = 0.05


@dataclass(frozen=True)
class ProbeCube(Task):
    def populate(self, spec: mujoco.MjSpec) -> None:
        add_free_box(spec, "cube", [CUBE_HALF] * 3, [0.85, 0.12, 0.1, 1.0], CUBE_MASS)

    def sample(self, seed: int) -> ObjectPoses:
        rng = self.rng(seed)
        x = rng.uniform(0.18, 0.26)
        y = rng.uniform(-0.16, -0.06)
        yaw = np.radians(rng.uniform(-45.0, 45.0))
        return {"cube": (np.array([x, y, rc.TABLE_Z + CUBE_HALF]), yaw_quat(yaw))}

    def success(
        self,
        objects: Sequence[tuple[str, int]],
        init_qpos: jax.Array,
        qpos: jax.Array,
        grip_open: jax.Array,
    ) -> dict[str, jax.Array]:
        adr = dict(objects)["cube"]
        lifted = qpos[adr + 2] - init_qpos[adr + 2] > LIFT_M
        closed = ~grip_open[-1]
        return {"lifted": lifted, "gripper_closed": closed, "success": lifted & closed}


TASK = ProbeCube(
    name="probe_cube",
    instruction="Pick up the red cube.",
    arms=("right",),
    step_budget=50,
    settle_steps=50,
)
