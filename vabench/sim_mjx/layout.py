"""Where the arms live in a compiled scene, and the JAX functions that read and write through it.

`ArmLayout` resolves joint and actuator names to addresses once, at construction. Through it:
the model-visible proprioception of a slot (`proprio_slot`, formatted by `proprio_fields` in the
fields of FACTS.md) and the joint references of an action (`with_refs`, `ctrl_sequence_slot`).
The three physics backends share these: MJX-JAX traces them, C MuJoCo calls them jitted on the
host, and the Warp backend has a Warp port of the same formulas (`warp.arm_indices`,
`warp.control`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import controller as ctl
from vabench.sim_mjx import jax_setup  # noqa: F401  (JAX configured before it compiles)
from vabench.sim_mjx import kinematics as kin
from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx.pytree import PyTree, pytree_dataclass


@dataclass(frozen=True)
class ArmLayout:
    """Where each present arm lives in qpos and ctrl; resolved once from names."""

    arms: tuple[str, ...]
    qpos: np.ndarray  # (A, 6) arm joint qpos addresses
    fingers: np.ndarray  # (A, 2) finger joint qpos addresses
    arm_act: np.ndarray  # (A, 6) actuator ids
    finger_act: np.ndarray  # (A, 2)

    @staticmethod
    def from_model(m: mujoco.MjModel) -> ArmLayout:
        def jadr(name: str) -> int:
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
            return int(m.jnt_qposadr[jid]) if jid >= 0 else -1

        def aid(name: str) -> int:
            return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, name)

        arms = tuple(a for a in rc.ARMS if jadr(f"{a}_waist") >= 0)
        if not arms:
            raise ValueError("the model has no vabench arm (joints named '<arm>_waist')")
        return ArmLayout(
            arms=arms,
            qpos=np.array([[jadr(f"{a}_{j}") for j in rc.ARM_JOINTS] for a in arms]),
            fingers=np.array([[jadr(f"{a}_{j}") for j in rc.FINGER_JOINTS] for a in arms]),
            arm_act=np.array([[aid(f"{a}_{j}") for j in rc.ARM_JOINTS] for a in arms]),
            finger_act=np.array([[aid(f"{a}_{j}") for j in rc.FINGER_JOINTS] for a in arms]),
        )

    def geometry(self, m: mujoco.MjModel) -> kin.ArmGeometry:
        per_arm = [kin.ArmGeometry.from_model(m, f"{a}_") for a in self.arms]
        return jax.tree.map(lambda *xs: jnp.stack(xs), *per_arm)

    def reset_ctrl(self, ctrl: np.ndarray, qpos: np.ndarray) -> np.ndarray:
        """Controls (..., nu) holding the arms where qpos (..., nq) puts them, fingers open:
        the references every backend starts a reset slot with."""
        out = np.array(ctrl, copy=True)
        out[..., self.arm_act] = qpos[..., self.qpos]
        out[..., self.finger_act] = rc.FINGER_OPEN
        return out


Arrays = jax.Array | np.ndarray
"""Proprioception is computed under jit (MJX-JAX) or on the host (C MuJoCo, Warp)."""


@pytree_dataclass
class Proprio(PyTree):
    gc: Arrays  # (..., A, 3) finger midpoint
    ee: Arrays  # (..., A, 3) control end effector
    rot: Arrays  # (..., A, 3, 3) columns: rx, ry, rz in the world frame
    quat: Arrays  # (..., A, 4) wxyz
    rpy: Arrays  # (..., A, 3) rad
    fingers: Arrays  # (..., A, 2) finger openings
    is_open: Arrays  # (..., A) bool


def proprio_slot(
    layout: ArmLayout, geoms: kin.ArmGeometry, qpos: jax.Array, grip_open: jax.Array
) -> Proprio:
    q = qpos[layout.qpos]
    fingers = qpos[layout.fingers]
    ee, rot, gc = jax.vmap(kin.gripper_points)(geoms, q, fingers)
    return Proprio(
        gc=gc,
        ee=ee,
        rot=rot,
        quat=jax.vmap(kin.mat_to_quat)(rot),
        rpy=jax.vmap(kin.mat_to_rpy)(rot),
        fingers=fingers,
        is_open=grip_open,
    )


def with_refs(layout: ArmLayout, ctrl: jax.Array, arm: jax.Array, fingers: jax.Array) -> jax.Array:
    return ctrl.at[layout.arm_act].set(arm).at[layout.finger_act].set(fingers)


def plan_from(
    layout: ArmLayout,
    geoms: kin.ArmGeometry,
    qpos: jax.Array,
    ctrl: jax.Array,
    cmd: ctl.ArmCommand,
    n_substeps: int,
    paced: bool = False,
) -> ctl.Plan:
    """The plan of one slot from its measured joints and the references it holds, its timing
    over `n_substeps` fixed or `paced` (`controller.pace`)."""
    return ctl.plan_slot(
        geoms,
        qpos[layout.qpos],
        qpos[layout.fingers],
        ctrl[layout.arm_act],
        ctrl[layout.finger_act],
        cmd,
        n_substeps,
        paced,
    )


def ctrl_sequence_slot(
    layout: ArmLayout,
    n_substeps: int,
    paced: bool,
    geoms: kin.ArmGeometry,
    qpos: jax.Array,
    ctrl: jax.Array,
    cmd: ctl.ArmCommand,
) -> tuple[jax.Array, ctl.Plan]:
    """The whole control sequence (n_substeps, nu) of one slot's action, for simulators that
    take open-loop controls (C MuJoCo, mujoco.rollout). Same plan and references as the MJX
    step."""
    plan = plan_from(layout, geoms, qpos, ctrl, cmd, n_substeps, paced)

    def at(k: jax.Array) -> jax.Array:
        arm, fingers = ctl.ctrl_at(plan, k)
        return with_refs(layout, ctrl, arm, fingers)

    return jax.vmap(at)(jnp.arange(n_substeps)), plan


def proprio_fields(p: Proprio, slot: int, arms: Sequence[str]) -> dict[str, dict[str, Any]]:
    """The model-visible proprioception of one slot, per arm, in the fields of FACTS.md."""

    def r(v: Any, nd: int) -> list[float]:
        return [round(float(x), nd) for x in v]

    out = {}
    for i, arm in enumerate(arms):
        rot = p.rot[slot, i]
        out[arm] = {
            "is_open": bool(p.is_open[slot, i]),
            "finger_center_xyz": r(p.gc[slot, i], 4),
            "control_eepose_xyz": r(p.ee[slot, i], 4),
            "control_eepose_rpy_deg": r(np.degrees(p.rpy[slot, i]), 2),
            "control_eepose_quat": r(p.quat[slot, i], 4),
            "local_axes_world": {k: r(rot[:, j], 4) for j, k in enumerate(("rx", "ry", "rz"))},
        }
    return out
