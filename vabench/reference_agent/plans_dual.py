"""The dual-arm families' plans: both arms parked, one look, then coordinated steps.

- lift_pot: each arm turns top-down with its fingers across its handle, hovers above it, both
  descend together (dual_gripper.move_world), close together, lift together: a closed chain
  (arm, pot, arm) moves as one only if both arms move in the same step.
- place_shoe: the arm on the shoe's side grasps it top-down across its upper, lifts it, turns
  it about the vertical until the toe points to -x (the instruction's "left"), carries it over
  the mat, lowers it until the sole is just above the table, opens and backs off.
- handover_horizontal_block: the arm on the block's side (the giver) grasps it top-down across
  its middle, lifts it, turns about its closing axis until its approach points forward (+y),
  which stands the block up between its fingers, and presents it just on the other side of
  x = 0; the other arm (the receiver) grasps the block's upper end top-down, the giver opens
  and backs off, the receiver carries the block further to its side.
"""

from __future__ import annotations

import math
from typing import Any

from vabench.reference_agent.geometry import TABLE_Z as T
from vabench.reference_agent.geometry import r4, wrap
from vabench.reference_agent.perception import Scene

Step = list[Any]

PARK = {"left": (-0.38, -0.25, 1.05), "right": (0.38, -0.25, 1.05)}
POT_HOVER = 0.06
POT_LIFT = 0.12  # the pot must rise > 79 mm; the arms lag a little under its weight
SHOE_GRASP_Z = 0.05  # GC above the table: the axis of the shoe's upper
SHOE_RELEASE_Z = 0.004  # the sole this far above the table when the gripper opens
SHOE_TARGET_TOE = 180.0  # toe towards -x
BLOCK_HALF = 0.015  # the block's half-thickness (30 mm square section)
BLOCK_HALF_LENGTH = 0.10
BLOCK_GRASP_DZ = 0.006  # GC above the block's centre: the fingertips clear the table
HANDOVER = (0.04, -0.05, 0.95)  # the block's centre, x towards the receiver's side
RECEIVER_BELOW_TOP = 0.025
RECEIVER_FINAL_X = 0.10
BACK_OFF = 0.06


def start_plan() -> list[Step]:
    """Open both, park both arms high on their own sides, fingers down, look from above."""
    return [
        ["dopen"],
        ["dgo", list(PARK["left"]), list(PARK["right"]), "zxy"],
        ["down:left"],
        ["down:right"],
        ["look", "topdown"],
        ["see"],
    ]


def look_again(looks: int) -> list[Step]:
    lift = 0.06 * looks
    left, right = ([*p[:2], r4(p[2] + lift)] for p in (PARK["left"], PARK["right"]))
    return [["dgo", left, right, "zxy"], ["look", "topdown"], ["see"]]


def _pt(x: float, y: float, z: float) -> list[float]:
    return [r4(x), r4(y), r4(z)]


def pot_plan(scene: Scene) -> list[Step]:
    pot = scene["pot"]
    a = math.radians(pot.heading)
    d = (pot.length / 2) * math.cos(a), (pot.length / 2) * math.sin(a)
    ends = [(pot.x - d[0], pot.y - d[1]), (pot.x + d[0], pot.y + d[1])]
    (lx, ly), (rx, ry) = sorted(ends)  # the left arm takes the handle on the -x side
    z = T + 0.085
    across = round(pot.heading + 90, 1)
    return [
        ["yaw:left", across, 180.0],
        ["yaw:right", across, 180.0],
        ["go:left", *_pt(lx, ly, z + POT_HOVER), "zxy"],
        ["go:right", *_pt(rx, ry, z + POT_HOVER), "zxy"],
        ["dgo", _pt(lx, ly, z), _pt(rx, ry, z), "z"],
        ["dclose"],
        ["dgo", _pt(lx, ly, z + POT_LIFT), _pt(rx, ry, z + POT_LIFT), "z"],
        ["retry"],
    ]


def shoe_plan(scene: Scene) -> list[Step]:
    shoe, mat = scene["shoe"], scene["mat"]
    arm = "right" if shoe.x > 0 else "left"
    z = T + SHOE_GRASP_Z
    turn = wrap(SHOE_TARGET_TOE - shoe.heading, 360.0)
    return [
        [f"yaw:{arm}", round(shoe.heading + 90, 1), 180.0],
        [f"go:{arm}", *_pt(shoe.x, shoe.y, z + 0.08), "zxy"],
        [f"go:{arm}", *_pt(shoe.x, shoe.y, z), "z"],
        [f"close:{arm}"],
        [f"go:{arm}", *_pt(shoe.x, shoe.y, z + 0.08), "z"],
        [f"turn:{arm}", round(turn, 1)],
        [f"go:{arm}", *_pt(mat.x, mat.y, z + 0.08), "xy"],
        [f"go:{arm}", *_pt(mat.x, mat.y, z + SHOE_RELEASE_Z), "z"],
        [f"open:{arm}"],
        [f"go:{arm}", *_pt(mat.x, mat.y, z + 0.08), "z"],
        ["retry"],
    ]


def block_plan(scene: Scene) -> list[Step]:
    block = scene["block"]
    giver = "right" if block.x > 0 else "left"
    receiver = "left" if giver == "right" else "right"
    side = 1.0 if receiver == "right" else -1.0
    z = T + BLOCK_HALF + BLOCK_GRASP_DZ
    hx, hy, hz = side * HANDOVER[0], HANDOVER[1], HANDOVER[2]
    # standing up turns the approach from down to +y, so the block's centre (BLOCK_GRASP_DZ
    # along the approach from GC) ends up that far in front of GC
    top = hz + BLOCK_HALF_LENGTH
    return [
        [f"yaw:{giver}", round(block.heading + 90, 1), 180.0],
        [f"go:{giver}", *_pt(block.x, block.y, z + 0.08), "zxy"],
        [f"go:{giver}", *_pt(block.x, block.y, z), "z"],
        [f"close:{giver}"],
        [f"go:{giver}", *_pt(block.x, block.y, hz), "z"],
        [f"fwd:{giver}", 45],
        [f"go:{giver}", *_pt(hx, hy, hz), "zxy"],
        [f"yaw:{receiver}", 0.0, 90.0],
        [f"go:{receiver}", *_pt(hx, hy + BLOCK_GRASP_DZ, top + 0.08), "zxy"],
        [f"go:{receiver}", *_pt(hx, hy + BLOCK_GRASP_DZ, top - RECEIVER_BELOW_TOP), "z"],
        [f"close:{receiver}"],
        [f"open:{giver}"],
        [f"go:{giver}", *_pt(hx, hy - BACK_OFF, hz), "y"],
        [f"go:{receiver}", *_pt(side * RECEIVER_FINAL_X, hy, top - RECEIVER_BELOW_TOP), "x"],
        ["retry"],
    ]
