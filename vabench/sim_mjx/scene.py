"""Scene construction: the table world, one or two arms, and a task's objects, as one MjModel.

Single-arm tasks build the scene with the right arm only: the left arm of the reference is
hidden and does not collide, and leaving it out of the model altogether halves the degrees of
freedom each MJX step integrates.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc

# Collision bits: the robot's gripper and the table collide with bit 1; objects also carry bit 2
# so that they, and only they, rest on the floor should they fall off the table.
OBJECT_CONTYPE = 3
OBJECT_CONAFFINITY = 3

Populate = Callable[[mujoco.MjSpec], None]


def build_spec(arms: Sequence[str] = rc.ARMS, populate: Populate | None = None) -> mujoco.MjSpec:
    """The scene as an editable spec: table world, the named arms, then `populate(spec)`."""
    unknown = sorted(set(arms) - set(rc.ARMS))
    if unknown or not arms:
        raise ValueError(f"arms must be a non-empty subset of {rc.ARMS}, got {list(arms)}")
    spec = mujoco.MjSpec.from_file(str(rc.TABLE_XML))
    floor = spec.geom("floor")
    floor.contype, floor.conaffinity = 2, 2
    half = rc.ARM_BASE_YAW / 2
    for arm in rc.ARMS:  # fixed order: left before right, whatever the caller's order
        if arm not in arms:
            continue
        arm_spec = mujoco.MjSpec.from_file(str(rc.ARM_XML))
        frame = spec.worldbody.add_frame(
            pos=rc.ARM_BASE_POS[arm], quat=[math.cos(half), 0.0, 0.0, math.sin(half)]
        )
        frame.attach_body(arm_spec.body("base"), f"{arm}_", "")
    if populate is not None:
        populate(spec)
    return spec


def build_model(arms: Sequence[str] = rc.ARMS, populate: Populate | None = None) -> mujoco.MjModel:
    return build_spec(arms, populate).compile()


def home_qpos(model: mujoco.MjModel) -> np.ndarray:
    """qpos with every arm present at HOME_Q, fingers open, objects at the model's default.

    (qpos0 itself stays untouched: MuJoCo measures hinge and slide angles from it.)
    """
    qpos = np.array(model.qpos0, copy=True)
    for arm in rc.ARMS:
        names = [*rc.ARM_JOINTS, *rc.FINGER_JOINTS]
        values = [*rc.HOME_Q, rc.FINGER_OPEN, rc.FINGER_OPEN]
        for name, value in zip(names, values, strict=True):
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{arm}_{name}")
            if jid >= 0:
                qpos[model.jnt_qposadr[jid]] = value
    return qpos


def add_free_box(
    spec: mujoco.MjSpec,
    name: str,
    half_size: Sequence[float],
    rgba: Sequence[float],
    mass: float,
    friction: float = 1.0,
) -> mujoco.MjsBody:
    """A free-floating box object (placed by the task's initial state, not here)."""
    body = spec.worldbody.add_body(name=name)
    body.add_freejoint(name=name)
    body.add_geom(
        name=name,
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=list(half_size),
        rgba=list(rgba),
        mass=mass,
        friction=[friction, 0.01, 0.0001],
        contype=OBJECT_CONTYPE,
        conaffinity=OBJECT_CONAFFINITY,
        condim=4,
    )
    return body


def rest_speeds(model: mujoco.MjModel) -> np.ndarray:
    """Each dof's rest speed (robot_constants.REST_SPEED): a free joint's three turning dofs
    REST_SPIN, every other dof REST_SPEED."""
    speeds = np.full(model.nv, rc.REST_SPEED)
    for jid in range(model.njnt):
        if model.jnt_type[jid] == mujoco.mjtJoint.mjJNT_FREE:
            adr = int(model.jnt_dofadr[jid])
            speeds[adr + 3 : adr + 6] = rc.REST_SPIN
    return speeds


def free_objects(model: mujoco.MjModel) -> list[tuple[str, int]]:
    """(name, qpos address) of every body with a free joint, in model order."""
    out = []
    for jid in range(model.njnt):
        if model.jnt_type[jid] == mujoco.mjtJoint.mjJNT_FREE:
            out.append((model.body(model.jnt_bodyid[jid]).name, int(model.jnt_qposadr[jid])))
    return out
