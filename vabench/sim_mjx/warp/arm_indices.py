"""`layout.py` for the Warp backend: the arms' addresses as device arrays, and the
proprioception kernel that reads the joints through them.

`Indices` holds `ArmLayout`'s qpos addresses and actuator ids; `arm_q` and `pair` read an arm's
joints (or references) of one slot through them, for these kernels and the plan's
(`control`). `proprio_kernel` is `layout.proprio_slot` over every slot and arm, with the
kinematics of `fk_ik`; tests/test_warp_control.py holds it to the JAX original.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from vabench.sim_mjx.layout import ArmLayout
from vabench.sim_mjx.warp.fk_ik import (
    ArmGeometryW,
    gripper_points,
    mat_to_quat,
    mat_to_rpy,
    vec6,
)


@dataclass
class Indices:
    """`ArmLayout` addresses as device arrays: (A, 6) and (A, 2) qpos addresses and ids."""

    arm_qadr: wp.array
    finger_qadr: wp.array
    arm_act: wp.array
    finger_act: wp.array


def layout_arrays(layout: ArmLayout, device: wp.context.Device | str) -> Indices:
    """The addresses of `layout` as int arrays on `device`."""

    def arr(x: np.ndarray) -> wp.array:
        return wp.array(np.asarray(x, np.int32), dtype=int, device=device)

    return Indices(
        arr(layout.qpos), arr(layout.fingers), arr(layout.arm_act), arr(layout.finger_act)
    )


@dataclass
class ProprioBuffers:
    """Per slot and arm: the fields of `layout.Proprio` (grip state apart)."""

    gc: wp.array  # (N, A) vec3
    ee: wp.array  # (N, A) vec3
    rot: wp.array  # (N, A) mat33
    quat: wp.array  # (N, A) vec4, w x y z
    rpy: wp.array  # (N, A) vec3
    fingers: wp.array  # (N, A) vec2

    @staticmethod
    def allocate(n: int, n_arms: int, device: wp.context.Device | str) -> ProprioBuffers:
        def z(dtype: type) -> wp.array:
            return wp.zeros((n, n_arms), dtype=dtype, device=device)

        return ProprioBuffers(
            z(wp.vec3), z(wp.vec3), z(wp.mat33), z(wp.vec4), z(wp.vec3), z(wp.vec2)
        )


@wp.func
def arm_q(qpos: wp.array2d(dtype=float), n: int, adr: wp.array2d(dtype=int), a: int) -> vec6:
    return vec6(
        qpos[n, adr[a, 0]],
        qpos[n, adr[a, 1]],
        qpos[n, adr[a, 2]],
        qpos[n, adr[a, 3]],
        qpos[n, adr[a, 4]],
        qpos[n, adr[a, 5]],
    )


@wp.func
def pair(x: wp.array2d(dtype=float), n: int, adr: wp.array2d(dtype=int), a: int) -> wp.vec2:
    return wp.vec2(x[n, adr[a, 0]], x[n, adr[a, 1]])


@wp.kernel
def proprio_kernel(
    geoms: wp.array(dtype=ArmGeometryW),
    qpos: wp.array2d(dtype=float),
    arm_qadr: wp.array2d(dtype=int),
    finger_qadr: wp.array2d(dtype=int),
    gc_out: wp.array2d(dtype=wp.vec3),
    ee_out: wp.array2d(dtype=wp.vec3),
    rot_out: wp.array2d(dtype=wp.mat33),
    quat_out: wp.array2d(dtype=wp.vec4),
    rpy_out: wp.array2d(dtype=wp.vec3),
    fingers_out: wp.array2d(dtype=wp.vec2),
):
    """Proprioception of arm a of slot n (layout.proprio_slot)."""
    n, a = wp.tid()
    fingers = pair(qpos, n, finger_qadr, a)
    ee, rot, gc = gripper_points(geoms[a], arm_q(qpos, n, arm_qadr, a), fingers)
    gc_out[n, a] = gc
    ee_out[n, a] = ee
    rot_out[n, a] = rot
    quat_out[n, a] = mat_to_quat(rot)
    rpy_out[n, a] = mat_to_rpy(rot)
    fingers_out[n, a] = fingers


def launch_proprio(
    geoms: wp.array, qpos: wp.array, idx: Indices, out: ProprioBuffers, grip_open: wp.array
) -> None:
    """Proprioception of every slot and arm into `out` (the grip state stays in grip_open)."""
    wp.launch(
        proprio_kernel,
        dim=grip_open.shape,
        inputs=[geoms, qpos, idx.arm_qadr, idx.finger_qadr],
        outputs=[out.gc, out.ee, out.rot, out.quat, out.rpy, out.fingers],
    )
