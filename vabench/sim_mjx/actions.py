"""Encoding validated robot actions into the batch's per-arm command arrays (host side).

A rotation is one command whatever its frame: a rotation vector in the current gripper frame,
which the controller turns about GC (R' = R exp(rotvec), <= 10 deg waypoints, refused whole
when one leaves the bounds). A world rotation by t about the world axis e is the same turn
about the local axis R^T e (exp(t [e]) R = R exp(t [R^T e])), so it is encoded as the rotation
vector t R^T e, R the orientation the controller starts from: the one of the measured joints
(`Proprio.rot`, what the model sees as `local_axes_world`). Every backend executes it as it
executes a local rotation; its intermediate poses turn about e too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from vabench import protocol as P
from vabench.sim_mjx import jax_setup  # noqa: F401  (JAX configured before it compiles)
from vabench.sim_mjx.controller import GRIP_CLOSE, GRIP_KEEP, GRIP_OPEN, ArmCommand

_WORLD_AXIS = {"x": 0, "y": 1, "z": 2}
_LOCAL_AXIS = {"rx": 0, "ry": 1, "rz": 2}


@dataclass
class CommandRows:
    """Host-side command arrays for a whole batch, filled slot by slot."""

    active: np.ndarray  # (N,) bool
    delta: np.ndarray  # (N, A, 3)
    rotvec: np.ndarray  # (N, A, 3)
    grip: np.ndarray  # (N, A) int32

    @staticmethod
    def idle(n_slots: int, n_arms: int) -> CommandRows:
        return CommandRows(
            active=np.zeros(n_slots, bool),
            delta=np.zeros((n_slots, n_arms, 3)),
            rotvec=np.zeros((n_slots, n_arms, 3)),
            grip=np.full((n_slots, n_arms), GRIP_KEEP, np.int32),
        )

    def to_device(self, dtype: np.dtype) -> ArmCommand:
        return ArmCommand(
            active=jnp.asarray(self.active),
            delta=jnp.asarray(self.delta, dtype),
            rotvec=jnp.asarray(self.rotvec, dtype),
            grip=jnp.asarray(self.grip),
        )


def _signed(sign: str, value: float) -> float:
    return value if sign == "+" else -value


def needs_orientation(action: object) -> bool:
    """Whether encoding `action` needs the slot's current gripper orientation."""
    return isinstance(action, P.RotateWorld)


def encode(
    action: P.AnyRobotAction,
    arms: Sequence[str],
    rows: CommandRows,
    slot: int,
    rot: np.ndarray | None = None,
) -> None:
    """Write one validated action into row `slot` (the action must fit `arms`). `rot`: the
    slot's gripper orientations (A, 3, 3), columns rx, ry, rz in the world, as the controller
    plans from them (the measured joints'); needed for a world rotation only."""
    index = {arm: i for i, arm in enumerate(arms)}
    rows.active[slot] = True
    if isinstance(action, P.MoveWorld):
        a = index[action.arm or arms[-1]]
        rows.delta[slot, a, _WORLD_AXIS[action.axis]] = _signed(
            action.sign, action.distance_mm / 1000.0
        )
    elif isinstance(action, P.RotateLocal):
        a = index[action.arm or arms[-1]]
        rows.rotvec[slot, a, _LOCAL_AXIS[action.axis]] = _signed(
            action.sign, math.radians(action.angle_deg)
        )
    elif isinstance(action, P.RotateWorld):
        if rot is None:
            raise ValueError("a world rotation is encoded from the gripper's orientation: pass rot")
        a = index[action.arm or arms[-1]]
        world_axis = np.zeros(3)
        world_axis[_WORLD_AXIS[action.axis]] = 1.0
        local_axis = np.asarray(rot[a], float).T @ world_axis
        local_axis /= np.linalg.norm(local_axis)  # R is orthonormal to float32 precision only
        rows.rotvec[slot, a] = _signed(action.sign, math.radians(action.angle_deg)) * local_axis
    elif isinstance(action, P.DualMove):
        for side, move in (("left", action.left), ("right", action.right)):
            rows.delta[slot, index[side], _WORLD_AXIS[move.axis]] = _signed(
                move.sign, move.distance_mm / 1000.0
            )
    else:
        value = GRIP_OPEN if action.opens else GRIP_CLOSE
        prefix = action.action.split("_gripper.")[0] if "_gripper." in action.action else None
        if prefix == "dual":
            targets = list(arms)
        elif prefix in ("left", "right"):
            targets = [prefix]
        else:
            targets = [action.arm or arms[-1]]
        for arm in targets:
            rows.grip[slot, index[arm]] = value
