"""The single-arm families' plans: what to do once the objects are located.

`family_of` names the family from the instruction; `start_plan` parks the arm where it hides
little and looks from above; `manipulation_plan` turns a located `Scene` into the steps that
do the task (step kinds: `executor`), ending in "retry" (a plan that runs to its end without
the episode ending has failed).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from vabench.reference_agent import geometry as g
from vabench.reference_agent.grasp_check import LIFT
from vabench.reference_agent.perception import Scene

PARK = (0.38, -0.25, 1.05)  # GC where the arm does not hide the objects from the topdown view
START_GC = (0.28, -0.20, 0.95)  # GC at reset (the robot state of the first observation)
T = g.TABLE_Z

Step = list[Any]


FAMILY_WORDS: tuple[tuple[tuple[str, ...], str], ...] = (
    (("bell",), "bell"),
    (("hammer",), "hammer"),
    (("bowl",), "cube_bowl"),
    (("stack",), "cube_on_cube"),
    (("green cube",), "cube_on_cube"),
    (("pad", "bottle"), "bottle_pad"),
    (("pad",), "cube_pad"),
    (("bottle", "upright"), "bottle_upright"),
    (("bottle",), "bottle_lying"),
    (("pen", "leaning"), "pen_leaning"),
    (("pen",), "pen"),
    (("cube",), "cube"),
)
"""The single-arm families by the words of their instruction: the first entry whose words all
appear wins, so the more specific entries come first."""


def named_family(instruction: str, words: Sequence[tuple[tuple[str, ...], str]]) -> str | None:
    """The family of the first entry of `words` whose words all appear in `instruction`."""
    s = instruction.lower()
    return next((family for need, family in words if all(w in s for w in need)), None)


def family_of(instruction: str) -> str | None:
    """The task family an instruction names, or None (dual-arm or unknown tasks)."""
    return named_family(instruction, FAMILY_WORDS)


def start_plan() -> list[Step]:
    """Open, park where the arm hides little, point the fingers down, look from above."""
    return [["open"], ["go", *PARK, "zxy"], ["down"], ["look", "topdown"], ["see"]]


def _r(v: float) -> float:
    return round(float(v), 4)


def topdown_grasp(
    x: float, y: float, z: float, heading: float, period: float, check: bool = True
) -> list[Step]:
    """Fingers straight down closing along `heading`, GC to (x, y, z), close, lift; with
    `check`, a short lift first and a look from the side: an empty grasp starts over."""
    x, y = _r(x), _r(y)
    lift: list[Step] = [["go", x, y, _r(z + 0.12), "z"]]
    if check:
        lift = [
            ["go", x, y, _r(z + LIFT), "z"],
            ["look", "side"],
            ["hold", [["retry"]]],
            *lift,
        ]
    return [
        ["down"],
        ["yaw", round(heading, 1), period],
        ["go", x, y, _r(z + 0.08), "xyz"],
        ["go", x, y, _r(z), "z"],
        ["close"],
        *lift,
    ]


def place_from_above(x: float, y: float, z: float, carry_z: float) -> list[Step]:
    """Carry the held object at `carry_z`, lower GC to `z` over (x, y), open, back off up."""
    x, y = _r(x), _r(y)
    return [
        ["go", x, y, _r(carry_z), "zxy"],
        ["go", x, y, _r(z), "z"],
        ["open"],
        ["go", x, y, _r(z + 0.08), "z"],
    ]


def manipulation_plan(family: str, scene: Scene) -> list[Step] | None:
    """The steps from the parked, looking arm to the end of the task (then "retry")."""
    o = scene["obj"]
    low = g.MIN_TOPDOWN_GC_Z
    if family == "cube":
        steps = topdown_grasp(o.x, o.y, T + 0.025, o.heading, 90.0)
    elif family == "pen":
        steps = topdown_grasp(o.x, o.y, max(low, T + 0.018), o.heading + 90, 180.0)
    elif family == "pen_leaning":
        steps = topdown_grasp(o.x, o.y, T + 0.042, o.heading + 90, 180.0)
    elif family == "bottle_lying":
        steps = topdown_grasp(o.x, o.y, T + 0.0314, o.heading + 90, 180.0)
    elif family in ("bottle_upright", "bottle_pad"):
        x, y, z = _r(o.x), _r(o.y), T + 0.06
        steps = [
            # turn where the episode starts (the arm reaches the side-grasp poses from there),
            # line up in x above the bottle, come in front of it, descend: the open fingers
            # straddle it and the palm stays in front
            ["go", *START_GC, "zyx"],
            ["fwd"],
            ["go", x, START_GC[1], START_GC[2], "x"],
            ["go", x, _r(y - 0.02), _r(z), "yz"],
            ["go", x, _r(y - 0.005), _r(z), "y"],
            ["close"],
            ["go", x, _r(y - 0.005), _r(z + (0.06 if family == "bottle_pad" else 0.10)), "z"],
        ]
        if family == "bottle_pad":
            d = scene["dest"]
            px, py = _r(d.x), _r(d.y - 0.005)
            steps += [
                ["go", px, py, _r(z + 0.06), "xy"],
                # 10 mm above resting: a side-held bottle may have slid a few mm down
                # between the fingers, and pressing it into the pad launches it on release
                ["go", px, py, _r(T + 0.006 + 0.06 + 0.010), "z"],
                ["open"],
                ["go", px, _r(py - 0.08), _r(T + 0.07), "y"],
                ["go", px, _r(py - 0.08), _r(T + 0.16), "z"],
            ]
    elif family == "bell":
        # the button's top is 76 mm above the table (the bell's press point); fingertips
        # (15 mm below GC) come down on it with the gripper closed, 6 mm past its top, then
        # 6 mm further if the first press did not count
        x, y, press = _r(o.x), _r(o.y), T + 0.076
        steps = [
            ["close"],
            ["down"],
            ["go", x, y, _r(press + 0.05 + g.FINGERTIP_BEYOND_GC), "zxy"],
            ["go", x, y, _r(press - 0.006 + g.FINGERTIP_BEYOND_GC), "z"],
            ["go", x, y, _r(press + 0.03), "z"],
            ["go", x, y, _r(press - 0.012 + g.FINGERTIP_BEYOND_GC), "z"],
            ["go", x, y, _r(press + 0.05), "z"],
        ]
    elif family == "hammer":
        # grasp across the handle 70 mm behind the striking face (its centre is 115 mm along
        # the handle from mid-handle and 50 mm to the -y side), lift, carry the face over the
        # block's top, lower the head onto it in small steps (a stiff arm pressing far into
        # an object launches it)
        d = scene["dest"]
        gx, gy, gz = o.x + 0.045, o.y, max(low, T + 0.017)
        # 4 mm short in y of the exact alignment (20 mm allowed): at the far end of the
        # block's range the arm is at the edge of its reach, and the longer move let the held
        # hammer slip
        cx, cy = d.x - 0.07, d.y + 0.05 - 0.004
        head = gz - T  # the head's underside is on the table while the hammer lies there
        steps = topdown_grasp(gx, gy, gz, 90.0, 180.0, check=False)[:-1]
        carry = T + 0.05 + head + 0.03
        steps += [["go", _r(gx), _r(gy), _r(gz + 0.10), "z"]]
        steps += [["go", _r(cx), _r(cy), _r(carry), "zxy"]]
        steps += [
            ["go", _r(cx), _r(cy), _r(T + 0.05 + head + dz), "z"]
            for dz in (0.006, 0.002, -0.001, -0.004, -0.007)
        ]
    elif family in ("cube_pad", "cube_on_cube", "cube_bowl"):
        half = 0.02 if family == "cube_bowl" else 0.025
        # held 5 mm above its centre the cube hangs below the finger pads instead of turning
        # between them (a tilted cube lands on an edge)
        above = 0.005
        steps = topdown_grasp(o.x, o.y, T + half + above, o.heading, 90.0)
        d = scene["dest"]
        if family == "cube_pad":
            steps += place_from_above(d.x, d.y, T + 0.006 + half + above + 0.002, T + 0.15)
        elif family == "cube_on_cube":
            # released 1 mm above resting: a drop of a few mm onto the base cube can make the
            # simulator launch both cubes (measured on the C backend)
            steps += [["yaw", round(d.heading, 1), 90.0]]
            steps += place_from_above(d.x, d.y, T + 0.05 + half + above + 0.001, T + 0.16)
        else:
            steps += place_from_above(d.x, d.y, T + 0.008 + 0.025 + half + above, T + 0.17)
    else:
        return None
    return [*steps, ["retry"]]
