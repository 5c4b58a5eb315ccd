"""Objects, poses and expert skills shared by the pen and bottle families
(grasp_single_pen, grasp_single_bottle, grasp_single_bottle_upright, grasp_pen_leaning_cube,
place_single_bottle_upright). No TASK here: not a family, so not in `families/`.

Objects (assets/objects/):
- pen_marker.xml: a marker 14 mm thick, 140 mm long; origin at its centre, long axis = local x,
  red cap at +x, black tip at -x; one colliding capsule.
- bottle_water.xml: a drink bottle 64 mm across, 168 mm tall; origin at the centre of its body,
  axis = local z, cap at +z; the body is a 16-sided prism (flat faces: lying, it does not roll).
- cube_blue_80.xml: the heavy 8 cm blue block a pen leans on.
- pad_green_130.xml: the 13 x 13 cm target pad of place_single_bottle_upright.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks.base import quat_mul, yaw_quat
from vabench.tasks.expert import Action, ExpertContext, View, horizontal, nearest, topdown

PEN_RADIUS = 0.007
PEN_HALF_SEG = 0.063  # half the distance between the capsule's end centres (140 mm overall)
BOTTLE_VERTEX_R = 0.032  # 16-gon prism: vertex radius
BOTTLE_FACE_R = BOTTLE_VERTEX_R * np.cos(np.pi / 16)  # centre to a flat face (31.4 mm)
BOTTLE_HALF_H = 0.06  # body half-height: origin above the bottom face
BLOCK_HALF = 0.04

# The lowest GC of a top-down grasp: the fingertips lie 15 mm below GC and the planner keeps the
# gripper 2 mm above the table top.
TOPDOWN_MIN_GC_Z = rc.TABLE_Z + rc.TABLE_CLEARANCE + 0.015


def axis_angle_quat(axis: np.ndarray | Sequence[float], angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis]


# -- poses -----------------------------------------------------------------------------------
def lying_pen_pose(x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """A pen lying on the table; yaw 0 = long axis along world x (left-right for the robot)."""
    return np.array([x, y, rc.TABLE_Z + PEN_RADIUS]), yaw_quat(yaw)


def leaning_pen_poses(
    x: float, y: float, yaw: float, lean: float, gap: float = -0.0002
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """A pen leaning on the 8 cm block: its lower end (the centre of the capsule's lower end
    cap, 7 mm above its contact with the table) at (x, y); the pen rises at `lean` above the
    horizontal, heading along (-sin yaw, cos yaw) (yaw 0 = away from the robot, +y); its upper
    end touches the block's near face (or, for steep leans, its barrel the block's top edge),
    `gap` short of contact; the block is turned by `yaw`. The default gap is a 0.2 mm overlap:
    a pen dropped from a gap onto its two contacts bounces off them and falls flat (a light
    capsule on two point contacts is neutrally stable about the line joining them)."""
    u = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    axis = np.cos(lean) * u + [0.0, 0.0, np.sin(lean)]
    lower = np.array([x, y, rc.TABLE_Z + PEN_RADIUS])
    pen_quat = quat_mul(yaw_quat(yaw + np.pi / 2), axis_angle_quat([0, 1, 0], -lean))
    h = 2 * BLOCK_HALF - PEN_RADIUS  # the block's top edge above the lower end's centre
    if 2 * PEN_HALF_SEG * np.sin(lean) < h:  # the upper end touches the near face
        reach = 2 * PEN_HALF_SEG * np.cos(lean) + PEN_RADIUS + gap + BLOCK_HALF
    else:  # the barrel rests on the near top edge
        reach = (h * np.cos(lean) + PEN_RADIUS) / np.sin(lean) + gap + BLOCK_HALF
    block = np.r_[lower[:2] + reach * u[:2], rc.TABLE_Z + BLOCK_HALF]
    return {
        "pen": (lower + PEN_HALF_SEG * axis, pen_quat),
        "block": (block, yaw_quat(yaw)),
    }


def lying_bottle_pose(x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """A bottle on its side, resting on a flat face of its prism; yaw 0 = axis along world +x
    (cap to the right)."""
    # Roll the prism so a face normal (mesh angle 11.25 deg) points along local x, then lay the
    # bottle down (local z -> world +x, local x -> world -z), then yaw.
    roll = axis_angle_quat([0, 0, 1], -np.pi / 16)
    down = axis_angle_quat([0, 1, 0], np.pi / 2)
    quat = quat_mul(yaw_quat(yaw), quat_mul(down, roll))
    return np.array([x, y, rc.TABLE_Z + BOTTLE_FACE_R]), quat


def upright_bottle_pose(x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
    return np.array([x, y, rc.TABLE_Z + BOTTLE_HALF_H]), np.array([1.0, 0.0, 0.0, 0.0])


def axis_heading(r: np.ndarray, column: int) -> float:
    """Heading in the world xy plane of an object's local axis (0 = x, 1 = y, 2 = z)."""
    return float(np.arctan2(r[1, column], r[0, column]))


# -- expert skills ---------------------------------------------------------------------------
def grasp_across(
    ctx: ExpertContext, arm: str, obj: str, long_axis: int, dz: float | None = None
) -> Iterator[Action]:
    """`topdown_grasp_at` closing across the object's long axis (its local axis `long_axis`,
    lying about horizontal), GC at the object's origin (or `dz` above it)."""
    across = axis_heading(ctx.view.mat(obj), long_axis) + np.pi / 2
    if dz is None:
        yield from topdown_grasp_at(ctx, arm, lambda v: v.pos(obj), across)
    else:
        yield from topdown_grasp_at(ctx, arm, lambda v: v.pos(obj) + [0.0, 0.0, dz], across)


def topdown_grasp_at(
    ctx: ExpertContext,
    arm: str,
    point: Callable[[View], np.ndarray],
    closing_yaw: float,
    hover: float = 0.08,
) -> Iterator[Action]:
    """Point the fingers straight down, closing along `closing_yaw` (either sign, whichever is
    the smaller turn), hover above `point`, descend onto it, close."""
    goal = nearest(ctx.view.arms[arm].rot, [topdown(closing_yaw), topdown(closing_yaw + np.pi)])
    yield from ctx.rotate_to(arm, goal)
    yield from ctx.move_to(arm, lambda v: point(v) + [0.0, 0.0, hover], order="zxy")
    yield from ctx.move_to(arm, lambda v: point(v) + [0.0, 0.0, hover], order="xyz")
    yield from ctx.move_to(arm, point, order="zxy")
    yield from ctx.grip(arm, close=True)


def side_grasp(
    ctx: ExpertContext,
    arm: str,
    point: Callable[[View], np.ndarray],
    standoff: float = 0.02,
) -> Iterator[Action]:
    """Horizontal approach along +y with the fingers closing along world x: turn, line up in x
    above the object (the open fingers then straddle it, the palm stays behind it), come to
    `standoff` in front of the point, descend to its height, slide in, close. Descending close
    to the object keeps the arm out of the poses near its base that it cannot reach."""
    turn = [horizontal(np.pi / 2), horizontal(np.pi / 2) @ np.diag([1.0, -1.0, -1.0])]
    yield from ctx.rotate_to(arm, nearest(ctx.view.arms[arm].rot, turn))
    yield from ctx.move_to(arm, lambda v: np.r_[point(v)[0], v.arms[arm].gc[1:]], order="x")
    yield from ctx.move_to(arm, lambda v: point(v) - [0.0, standoff, 0.0], order="yz")
    yield from ctx.move_to(arm, point, order="yxz")
    yield from ctx.grip(arm, close=True)
