"""The basket task: one object at a time, then back to the observation pose to look again.

From the observation pose (GC far to the right and behind the objects, high, fingers down: the
arm then reaches into the image from its lower edge, below every object, and the view holds
the whole near half of the table and the basket) the agent locates the basket and the objects
still outside it (`perception_basket`), takes the first of them in `ORDER`, and:
hovers above it, turns top-down across it, descends, closes, rises a little and looks from the
side (an empty grasp: back to look again), lifts above everything, turns it
square to the basket (long objects along the basket's y, cubes with faces along its axes),
carries it over its slot in the basket, lowers it (the upright bottle onto the floor, the pen
to just above it) or lets it drop from just above the rim, opens, rises and goes back to look.
An object still outside after `MAX_ATTEMPTS` tries is left; with nothing left to place, stop.

The order is the tall bottle first (afterwards nothing on the table is taller than the palm
above a low grasp), the pen while the fingers still have room to reach down into the basket,
then what is dropped in from the rim. The slots keep the objects' footprints apart inside the
260 x 200 mm interior.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from vabench.reference_agent.geometry import TABLE_Z as T
from vabench.reference_agent.geometry import r4, wrap
from vabench.reference_agent.grasp_check import LIFT
from vabench.reference_agent.perception import Scene, Seen

Step = list[Any]

OBS = (0.50, -0.32, 1.12)  # GC where the agent looks from
HOVER_Z = T + 0.237  # above the upright bottle with the fingertips 30 mm clear; higher, the
# arm cannot turn its fingers straight down over objects close to its base
REACH_X, REACH_Y = (-0.05, 0.45), (-0.32, 0.10)  # where an object can be picked up again
UPRIGHT_HEIGHT = 0.168
CLEARANCE = 0.03
ORDER = ("upright_bottle", "pen", "bottle", "cube", "small_cube")
MAX_ATTEMPTS = 2
SLOTS = {  # footprint centres in the basket's frame
    "upright_bottle": (-0.085, 0.055),
    "cube": (-0.085, -0.055),
    "small_cube": (-0.02, -0.04),
    "pen": (0.02, 0.01),
    "bottle": (0.08, 0.0),
}
FLOOR_Z = 0.024  # the basket's floor top above the table
RIM_Z = 0.079
GRASP_Z = {  # GC above the table
    "upright_bottle": 0.113,  # 53 mm above its centre: the palm clears the neck
    "pen": 0.018,  # the lowest the fingertips allow
    "bottle": 0.0314,  # its axis
    "cube": 0.020,  # 5 mm below the centre: the pads squeeze across its centre of mass
    "small_cube": 0.025,  # 5 mm above the centre
}
RELEASE_Z = {  # GC above the table when the gripper opens
    "upright_bottle": FLOOR_Z + 0.06 + 0.053 + 0.003,  # standing on the floor
    "pen": FLOOR_Z + 0.003 + 0.018,  # lying 3 mm above the floor
    "bottle": FLOOR_Z + 0.005 + 0.0314,  # lying 5 mm above the floor: dropped, it rolls
}
DROP_Z = RIM_Z + 0.008 + 0.015  # others: the fingertips 8 mm above the rim


def start_plan() -> list[Step]:
    """From the start (or after a failure: fingers straight down first, the arm may be stuck
    tilted) to the observation pose, then look."""
    return [["open"], ["down"], ["go", *OBS, "zxy"], ["down"], ["look", "topdown"], ["see"]]


def look_again(looks: int) -> list[Step]:
    return [["go", *OBS[:2], r4(OBS[2] + 0.04 * looks), "zxy"], ["look", "topdown"], ["see"]]


def _reachable(o: Seen) -> bool:
    """An object knocked beyond the basket or off the near half is left where it is."""
    return REACH_X[0] <= o.x <= REACH_X[1] and REACH_Y[0] <= o.y <= REACH_Y[1]


def _grip(kind: str, heading: float) -> tuple[float, float]:
    """(ry heading, period) of a top-down grasp across the object."""
    if kind == "upright_bottle":
        return 11.25, 22.5  # across two flat faces of its 16-gon body
    if kind in ("cube", "small_cube"):
        return round(heading, 1), 90.0
    return round(heading + 90, 1), 180.0


def _square_turn(kind: str, heading: float) -> float:
    """The turn (deg, about the vertical) that lines the held object up with the basket."""
    if kind == "upright_bottle":
        return 0.0
    if kind in ("cube", "small_cube"):
        return wrap(-heading, 90.0)
    return wrap(90.0 - heading, 180.0)


def basket_plan(scene: Scene, memo: dict[str, Any]) -> list[Step]:
    basket = scene["basket"]
    attempts: dict[str, int] = memo.setdefault("attempts", {})
    todo = [
        k
        for k in ORDER
        if k in scene and attempts.get(k, 0) < MAX_ATTEMPTS and _reachable(scene[k])
    ]
    if not todo:
        left = [k for k in ORDER if k in scene]
        return [["stop", f"objects left outside the basket: {left}" if left else "all placed"]]
    kind = todo[0]
    attempts[kind] = attempts.get(kind, 0) + 1
    o = scene[kind]
    ry, period = _grip(kind, o.heading)
    turn = _square_turn(kind, o.heading)
    # the footprint's middle lies `offset` along the object's heading from the grasp; after
    # the turn that vector has turned too
    a = math.radians(o.heading + turn)
    shift = o.offset * np.array([math.cos(a), math.sin(a)])
    sx, sy = np.array([basket.x, basket.y]) + SLOTS[kind] - shift
    release = RELEASE_Z.get(kind, DROP_Z)
    gz = T + GRASP_Z[kind]
    # carried with its bottom 30 mm above the rim (the upright bottle, first) or above the
    # upright bottle standing in the basket (the rest): the lowest that clears everything,
    # since the arm's reach shrinks with height over the basket's far corner
    above = RIM_Z if kind == "upright_bottle" else FLOOR_Z + UPRIGHT_HEIGHT
    carry = r4(T + above + CLEARANCE + GRASP_Z[kind])
    steps: list[Step] = [
        ["go", OBS[0], OBS[1], r4(HOVER_Z), "z"],
        ["go", r4(o.x), r4(o.y), r4(HOVER_Z), "yx"],
        ["down"],
        ["yaw", ry, period],
        ["go", r4(o.x), r4(o.y), r4(gz + 0.08), "z"],
        ["go", r4(o.x), r4(o.y), r4(gz), "z"],
        ["close"],
        ["go", r4(o.x), r4(o.y), r4(gz + LIFT), "z"],
        ["look", "side"],
        ["hold", look_from_obs()],  # an empty grasp: look again, that object again
        ["go", r4(o.x), r4(o.y), carry, "z"],
    ]
    if abs(turn) >= 1.0:
        steps.append(["turn", round(turn, 1)])
    steps += [
        ["go", r4(sx), r4(sy), carry, "xy"],
        ["go", r4(sx), r4(sy), r4(T + release), "z"],
        ["open"],
        ["go", r4(sx), r4(sy), carry, "z"],
        *look_from_obs(),
    ]
    return steps


def look_from_obs() -> list[Step]:
    """Back to the observation pose: the fingers closing along x again (as where the episode
    starts: turned by a quarter, the wrist cannot reach the pose), towards the robot first
    (high over the basket's far side the arm is at the edge of its reach), then out to the
    right, then up."""
    return [
        ["down"],
        ["yaw", 0.0, 180.0],
        ["go", *OBS, "yxz"],
        ["down"],
        ["look", "topdown"],
        ["see"],
    ]
