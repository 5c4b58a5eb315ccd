"""What a task family provides: scene objects, a seeded sampler, a success predicate.

The full interface (latched flags, checkpoints, experts, verified seeds) grows with the task
suite; this base holds what the simulator core and the replay CLI need.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import scene

ObjectPoses = dict[str, tuple[np.ndarray, np.ndarray]]  # name -> (pos (3,), quat wxyz (4,))


def yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


@dataclass(frozen=True)
class Task:
    """Base class of a task family. Subclasses override `populate`, `sample` and `success`."""

    name: str
    instruction: str
    arms: tuple[str, ...] = ("right",)
    step_budget: int = 50
    settle_steps: int = 0

    def populate(self, spec: mujoco.MjSpec) -> None:
        """Add the task's objects to the scene spec."""

    def sample(self, seed: int) -> ObjectPoses:
        """Evaluator-only initial object poses; deterministic in the seed alone."""
        return {}

    def build_model(self) -> mujoco.MjModel:
        return scene.build_model(self.arms, self.populate)

    def initial_qpos(self, model: mujoco.MjModel, seed: int) -> np.ndarray:
        qpos = scene.home_qpos(model)
        adr = dict(scene.free_objects(model))
        for name, (pos, quat) in self.sample(seed).items():
            qpos[adr[name] : adr[name] + 3] = pos
            qpos[adr[name] + 3 : adr[name] + 7] = quat
        return qpos

    def success(
        self,
        objects: Sequence[tuple[str, int]],
        init_qpos: jax.Array,
        qpos: jax.Array,
        grip_open: jax.Array,
    ) -> dict[str, jax.Array]:
        """Named sub-checks plus 'success' for one slot (jittable)."""
        return {"success": jnp.array(False)}

    @staticmethod
    def rng(seed: int) -> np.random.Generator:
        return np.random.default_rng(seed)
