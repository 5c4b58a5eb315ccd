"""The basket task: one object at a time, then back to the observation pose to look again.

From the observation pose (GC far to the right and behind the objects, high, fingers down: the
arm then reaches into the image from its lower edge, below every object, and the view holds
the whole near half of the table and the basket) the agent locates the basket and the objects
still outside it (`perception_basket`), takes the first of them in `ORDER`, and:
hovers above it, turns top-down across it, descends, closes, lifts above everything, turns it
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
from vabench.reference_agent.perception import Scene

Step = list[Any]

OBS = (0.50, -0.32, 1.12)  # GC where the agent looks from
HOVER_Z = 1.05
CARRY_Z = 1.08
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
}
DROP_Z = RIM_Z + 0.008 + 0.015  # others: the fingertips 8 mm above the rim


def start_plan() -> list[Step]:
    return [["open"], ["go", *OBS, "zxy"], ["down"], ["look", "topdown"], ["see"]]


def look_again(looks: int) -> list[Step]:
    return [["go", *OBS[:2], r4(OBS[2] + 0.04 * looks), "zxy"], ["look", "topdown"], ["see"]]


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
    todo = [k for k in ORDER if k in scene and attempts.get(k, 0) < MAX_ATTEMPTS]
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
    steps: list[Step] = [
        ["go", OBS[0], OBS[1], HOVER_Z, "z"],
        ["go", r4(o.x), r4(o.y), HOVER_Z, "yx"],
        ["down"],
        ["yaw", ry, period],
        ["go", r4(o.x), r4(o.y), r4(gz + 0.08), "z"],
        ["go", r4(o.x), r4(o.y), r4(gz), "z"],
        ["close"],
        ["go", r4(o.x), r4(o.y), CARRY_Z, "z"],
    ]
    if abs(turn) >= 1.0:
        steps.append(["turn", round(turn, 1)])
    steps += [
        ["go", r4(sx), r4(sy), CARRY_Z, "xy"],
        ["go", r4(sx), r4(sy), r4(T + release), "z"],
        ["open"],
        ["go", r4(sx), r4(sy), CARRY_Z, "z"],
        ["go", *OBS, "zxy"],
        ["down"],
        ["look", "topdown"],
        ["see"],
    ]
    return steps
