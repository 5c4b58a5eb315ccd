"""Encoding validated robot actions into the batch's per-arm command arrays (host side)."""

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


def encode(
    action: P.MoveWorld | P.RotateLocal | P.Aperture | P.DualMove,
    arms: Sequence[str],
    rows: CommandRows,
    slot: int,
) -> None:
    """Write one validated action into row `slot` (the action must fit `arms`)."""
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
