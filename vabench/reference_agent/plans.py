"""The agent's plans: a list of steps per task family, executed one decision at a time.

A plan is a JSON list of steps carried in the memo (see `request`), with the index of the
current step. Each decision runs `decide`: a step that the observation shows done (GC at its
target, the gripper turned, the aperture set) is skipped; the first that is not yields the next
action. Moves are closed-loop on the robot state (GC from `finger_center_xyz`), so a clipped or
partly executed move is simply continued.

Steps:
  ["down"]                  turn about ry or rz until rx points straight down
  ["fwd"]                   the same until rx points along world +y (side grasps)
  ["yaw", heading, period]  turn about rx until ry has `heading` (deg) modulo `period`
  ["go", x, y, z, order]    move GC there, one world axis at a time in `order` ("xyz", "z")
  ["open"], ["close"]       the gripper
  ["look", view]            a camera view (fresh image of the current scene)
  ["see"]                   locate the family's objects in the topdown image; on success the
                            rest of the plan is replaced by the family's manipulation plan
  ["retry"]                 the task did not end: start over (park, look, see), at most
                            `MAX_TRIES` times
  ["stop"]
A step the planner fails `MAX_PLANNER_FAILS` times (rejected, or GC left where it was) also
starts over: the arm may reach the same target from the parking pose.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from vabench.reference_agent import geometry as g
from vabench.reference_agent.perception import Scene, locate, looks_like_scene
from vabench.reference_agent.request import Observation
from vabench.reference_agent.vision import decode

PARK = (0.38, -0.25, 1.05)  # GC where the arm does not hide the objects from the topdown view
START_GC = (0.28, -0.20, 0.95)  # GC at reset (the robot state of the first observation)
MOVE_TOL = 0.001  # m
TURN_TOL = 0.7  # deg (actions turn by at least 1 deg)
MAX_MOVE_MM = 100
MAX_TURN_DEG = 90
MAX_TRIES = 3
MAX_LOOKS = 2  # failed looks in a row before giving up
MAX_PLANNER_FAILS = 2  # failed attempts at one step before starting over
T = g.TABLE_Z

Action = dict[str, Any]
Step = list[Any]


def family_of(instruction: str) -> str | None:
    """The task family an instruction names, or None (dual-arm or unknown tasks)."""
    s = instruction.lower()
    if "bell" in s:
        return "bell"
    if "hammer" in s:
        return "hammer"
    if "bowl" in s:
        return "cube_bowl"
    if "stack" in s or "green cube" in s:
        return "cube_on_cube"
    if "pad" in s:
        return "bottle_pad" if "bottle" in s else "cube_pad"
    if "bottle" in s:
        return "bottle_upright" if "upright" in s else "bottle_lying"
    if "pen" in s:
        return "pen_leaning" if "leaning" in s else "pen"
    if "cube" in s:
        return "cube"
    return None


def start_plan() -> list[Step]:
    """Open, park where the arm hides little, point the fingers down, look from above."""
    return [["open"], ["go", *PARK, "zxy"], ["down"], ["look", "topdown"], ["see"]]


def _r(v: float) -> float:
    return round(float(v), 4)


def topdown_grasp(x: float, y: float, z: float, heading: float, period: float) -> list[Step]:
    """Fingers straight down closing along `heading`, GC to (x, y, z), close, lift."""
    x, y = _r(x), _r(y)
    return [
        ["down"],
        ["yaw", round(heading, 1), period],
        ["go", x, y, _r(z + 0.08), "xyz"],
        ["go", x, y, _r(z), "z"],
        ["close"],
        ["go", x, y, _r(z + 0.12), "z"],
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
        steps = topdown_grasp(gx, gy, gz, 90.0, 180.0)[:-1]
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


# -- executing one step ------------------------------------------------------------------------


def _move(axis: str, delta_m: float) -> Action:
    mm = max(1.0, min(MAX_MOVE_MM, round(abs(delta_m) * 1000, 1)))
    return {
        "action": "gripper.move_world",
        "axis": axis,
        "sign": "+" if delta_m > 0 else "-",
        "distance_mm": mm,
    }


def _turn(axis: str, deg: float) -> Action:
    a = max(1.0, min(MAX_TURN_DEG, round(abs(deg), 1)))
    return {
        "action": "gripper.rotate_local",
        "axis": axis,
        "sign": "+" if deg > 0 else "-",
        "angle_deg": a,
    }


def _stuck(kind: str, gc: np.ndarray, memo: dict[str, Any]) -> bool:
    """A move that left GC where it was (rejected or clipped to the workspace)."""
    at = memo.get("at")
    return kind == "go" and at is not None and float(np.abs(gc - np.array(at)).max()) < 5e-4


def decide(obs: Observation, family: str) -> tuple[Action | None, str, dict[str, Any]]:
    """(action or None for stop, a reason, the memo to carry) for this observation."""
    memo: dict[str, Any] = dict(obs.memo) if obs.memo.get("f") == family else {"f": family}
    plan: list[Step] = memo.get("plan") or start_plan()
    i = int(memo.get("i", 0))
    if obs.image is None or not looks_like_scene(decode(obs.image)):
        # every view of this scene shows the table; an image that does not (noise, a broken
        # render) is no ground for any action: look again, then give up
        blind = int(memo.get("blind", 0)) + 1
        if blind > MAX_LOOKS:
            return None, "the images do not show the scene", memo
        memo.update(plan=plan, i=i, blind=blind, last=None)
        return {"action": "camera.view_topdown"}, "image unreadable: look again", memo
    memo.pop("blind", None)
    arm = obs.arms["right"]
    last = memo.get("last")
    for _ in range(len(plan) + 4):
        if i >= len(plan):
            return None, "plan finished", {**memo, "plan": plan, "i": i}
        step = plan[i]
        kind = step[0]
        out: Action | None = None
        fails = int(memo.get("fails", 0))
        if last == [kind, i] and (arm.last_planner is False or _stuck(kind, arm.gc, memo)):
            fails += 1
        if fails >= MAX_PLANNER_FAILS and kind != "retry":
            # the planner cannot do this step from here: start over from the parked pose
            plan, i, last = [["retry"]], 0, None
            memo.pop("fails", None)
            continue
        memo["fails"] = fails
        if kind == "down" or kind == "fwd":
            goal = np.array([0.0, 0.0, -1.0]) if kind == "down" else np.array([0.0, 1.0, 0.0])
            if g.angle_between(arm.rx, goal) > TURN_TOL:
                # about ry or rz, whichever brings rx closer: a tilt left about rz would put
                # one fingertip lower than the other
                by_y = g.turn_to_align(arm.rx, arm.ry, goal)
                by_z = g.turn_to_align(arm.rx, arm.rz, goal)
                out = _turn("ry", by_y) if abs(by_y) >= abs(by_z) else _turn("rz", by_z)
        elif kind == "yaw":
            turn = g.yaw_turn(arm.rx, arm.ry, float(step[1]), float(step[2]))
            if abs(turn) > TURN_TOL:
                out = _turn("rx", turn)
        elif kind == "go":
            err = np.array(step[1:4], float) - arm.gc
            for axis in step[4]:
                k = "xyz".index(axis)
                if abs(err[k]) > MOVE_TOL:
                    out = _move(axis, float(err[k]))
                    break
        elif kind in ("open", "close"):
            if arm.is_open != (kind == "open") and last != [kind, i]:
                out = {"action": f"gripper.{kind}"}
        elif kind == "look":
            memo.update(plan=plan, i=i + 1, last=["look", i])
            return {"action": f"camera.view_{step[1]}"}, f"look: {step[1]}", memo
        elif kind == "see":
            return _see(obs, family, plan, i, memo)
        elif kind == "retry":
            tries = int(memo.get("try", 0)) + 1
            if tries >= MAX_TRIES:
                return None, "the task did not end after every try", memo
            plan, i, memo = start_plan(), 0, {"f": family, "try": tries}  # a fresh memo
            continue
        elif kind == "stop":
            return None, "stop step", memo
        if out is not None:
            memo.update(plan=plan, i=i, last=[kind, i], at=[_r(v) for v in arm.gc])
            return out, f"step {i}: {kind}", memo
        i += 1
        memo.pop("fails", None)
        last = None
    return None, "no progress", memo


def _see(
    obs: Observation, family: str, plan: list[Step], i: int, memo: dict[str, Any]
) -> tuple[Action | None, str, dict[str, Any]]:
    arm = obs.arms["right"]
    scene = None
    if obs.image is not None and obs.view == "topdown":
        hsv = decode(obs.image)
        cam = g.topdown_camera(tuple(arm.gc), hsv.shape[1], hsv.shape[0])  # type: ignore[arg-type]
        scene = locate(family, hsv, cam)
    if scene is None:
        looks = int(memo.get("looks", 0)) + 1
        if looks > MAX_LOOKS:
            return None, "the objects are not visible in the topdown view", memo
        memo.update(plan=plan, i=i, looks=looks, last=["look", i])
        return {"action": "camera.view_topdown"}, "objects not found: look again", memo
    rest = manipulation_plan(family, scene)
    if rest is None:
        return None, f"no plan for {family}", memo
    seen = {k: [_r(v.x), _r(v.y), round(v.heading, 1)] for k, v in scene.items()}
    memo = {k: v for k, v in memo.items() if k != "looks"}
    memo.update(plan=rest, i=0, seen=seen, last=None)
    return decide(dataclasses.replace(obs, memo=memo), family)
