"""Attaching the task objects authored in `assets/objects/` to a scene spec.

Every object file is an MJCF model whose worldbody holds one root body with a free joint. The
root body takes the task's object name (the name the sampler, predicates and expert use); its
geoms and child bodies get that name as a prefix. Object geoms collide with the gripper and the
table (bit 1) and with the floor (bit 2) should they fall; visual-only geoms carry contype 0.
Collision shapes are restricted to what MJX collides efficiently with box fingers and a plane
table: boxes, capsules, spheres and small convex meshes (cylinders are convex meshes).
"""

from __future__ import annotations

from pathlib import Path

import mujoco

from vabench.sim_mjx import robot_constants as rc

OBJECTS = rc.ASSETS / "objects"


def object_path(file: str) -> Path:
    path = OBJECTS / file
    if not path.exists():
        raise FileNotFoundError(f"object model {path} does not exist")
    return path


def attach_object(spec: mujoco.MjSpec, file: str, name: str) -> mujoco.MjsBody:
    """Attach the object of `assets/objects/<file>` as a free body called `name`."""
    obj = mujoco.MjSpec.from_file(str(object_path(file)))
    roots = obj.worldbody.bodies
    if len(roots) != 1:
        raise ValueError(f"{file}: expected one root body in the worldbody, found {len(roots)}")
    frame = spec.worldbody.add_frame()
    body = frame.attach_body(roots[0], f"{name}_", "")
    body.name = name
    joints = body.joints
    if len(joints) != 1 or joints[0].type != mujoco.mjtJoint.mjJNT_FREE:
        raise ValueError(f"{file}: the root body must have exactly one free joint")
    joints[0].name = name
    return body
