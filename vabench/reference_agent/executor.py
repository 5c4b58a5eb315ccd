"""Executing a plan one decision at a time, closed-loop on the robot state.

A plan is a JSON list of steps carried in the memo (see `request`), with the index of the
current step. Each decision runs `decide`: a step that the observation shows done (GC at its
target, the gripper turned, the aperture set) is skipped; the first that is not yields the next
action. Moves are closed-loop on the robot state (GC from `finger_center_xyz`), so a clipped or
partly executed move is simply continued.

Steps (`kind` may name an arm as `kind:left` / `kind:right`; without one it is the right arm,
the only arm of single-arm tasks):
  ["down"] / ["fwd", max_deg]  turn about ry or rz until rx points straight down / along +y
  ["yaw", heading, period]     turn about rx until ry has `heading` (deg) modulo `period`
  ["turn", deg]                turn about the vertical by `deg` (counter-clockwise seen from
                               above) from where the gripper is when the step is reached
  ["go", x, y, z, order]       move GC there, one world axis at a time in `order` ("xyz", "z")
  ["dgo", [l], [r], order]     both arms at once (dual_gripper.move_world), each to its target
  ["open"], ["close"]          one gripper; ["dopen"], ["dclose"] both at once
  ["look", view]               a camera view (active protocol); the passive protocol's five
                               views come with every observation, so there it is a no-op
  ["see"]                      locate the family's objects; on success the rest of the plan is
                               replaced by the family's manipulation plan (`families`)
  ["hold", [steps]]            the side view shows the object in the fingers (`grasp_check`);
                               if not, open and go on with `steps` (look again, start over)
  ["retry"]                    the task did not end: start over (park, look, see), at most
                               `MAX_TRIES` times
  ["stop"]
A step the planner fails `MAX_PLANNER_FAILS` times (rejected, or GC left where it was) also
starts over: the arm may reach the same target from the parking pose.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from vabench.reference_agent import families, grasp_check
from vabench.reference_agent import geometry as g
from vabench.reference_agent.perception import looks_like_scene
from vabench.reference_agent.request import Observation
from vabench.reference_agent.vision import decode

MOVE_TOL = 0.001  # m
TURN_TOL = 0.7  # deg (actions turn by at least 1 deg)
MAX_MOVE_MM = 100
REFUSED_MOVE_MM = 20  # the longest move after one the planner refused
MAX_TURN_DEG = 90
MAX_TRIES = 3
MAX_LOOKS = 2  # failed looks in a row before giving up
MAX_PLANNER_FAILS = 2  # failed attempts at one step before starting over

Action = dict[str, Any]
Step = list[Any]
Decision = tuple[Action | None, str, dict[str, Any]]


def split_kind(step: Step) -> tuple[str, str]:
    kind, _, arm = str(step[0]).partition(":")
    return kind, arm or "right"


def _move(axis: str, delta_m: float, max_mm: float = MAX_MOVE_MM) -> dict[str, Any]:
    mm = max(1.0, min(max_mm, round(abs(delta_m) * 1000, 1)))
    return {"axis": axis, "sign": "+" if delta_m > 0 else "-", "distance_mm": mm}


def _with_arm(action: Action, arm: str, dual: bool) -> Action:
    return {**action, "arm": arm} if dual else action


def _turn(axis: str, deg: float, max_deg: float = MAX_TURN_DEG) -> Action:
    a = max(1.0, min(max_deg, round(abs(deg), 1)))
    return {
        "action": "gripper.rotate_local",
        "axis": axis,
        "sign": "+" if deg > 0 else "-",
        "angle_deg": a,
    }


def _next_axis(target: np.ndarray, gc: np.ndarray, order: str) -> tuple[str, float] | None:
    err = np.asarray(target, float) - gc
    for axis in order:
        k = "xyz".index(axis)
        if abs(err[k]) > MOVE_TOL:
            return axis, float(err[k])
    return None


def _gcs(obs: Observation) -> dict[str, list[float]]:
    return {name: [g.r4(v) for v in arm.gc] for name, arm in obs.arms.items()}


def _stuck(kind: str, arm: str, obs: Observation, memo: dict[str, Any]) -> bool:
    """A move that left GC where it was (rejected or clipped to the workspace)."""
    at = memo.get("at")
    if kind not in ("go", "dgo") or not isinstance(at, dict):
        return False
    names = list(obs.arms) if kind == "dgo" else [arm]
    return all(
        n in at and float(np.abs(obs.arms[n].gc - np.array(at[n])).max()) < 5e-4 for n in names
    )


def _step_action(
    obs: Observation, step: Step, kind: str, arm_name: str, avoid: str | None = None
) -> Action | None:
    """The action that advances `step`, or None when the observation shows it done."""
    dual = obs.dual
    arm = obs.arms.get(arm_name)
    if kind in ("down", "fwd"):
        assert arm is not None
        goal = np.array([0.0, 0.0, -1.0]) if kind == "down" else np.array([0.0, 1.0, 0.0])
        if g.angle_between(arm.rx, goal) <= TURN_TOL:
            return None
        # about ry or rz, whichever brings rx closer (ry on a tie: a tilt about rz would put
        # one fingertip lower than the other)
        turns = {"ry": g.turn_to_align(arm.rx, arm.ry, goal)}
        turns["rz"] = g.turn_to_align(arm.rx, arm.rz, goal)
        left = {
            k: g.angle_between(g.rotate(arm.rx, getattr(arm, k), a), goal) for k, a in turns.items()
        }
        axis = "ry" if left["ry"] <= left["rz"] + 1.0 else "rz"
        max_deg = float(step[1]) if len(step) > 1 else MAX_TURN_DEG
        return _with_arm(_turn(axis, turns[axis], max_deg), arm_name, dual)
    if kind == "yaw":
        assert arm is not None
        turn = g.yaw_turn(arm.rx, arm.ry, float(step[1]), float(step[2]))
        return _with_arm(_turn("rx", turn), arm_name, dual) if abs(turn) > TURN_TOL else None
    if kind == "go":
        assert arm is not None
        # after a move the planner refused, the other axes first: a target out of reach
        # from here along one axis is often within reach after a move along another
        order = "".join(sorted(step[4], key=lambda a: a == avoid))
        nxt = _next_axis(np.array(step[1:4], float), arm.gc, order)
        if nxt is None:
            return None
        # and shorter: the planner rejects a whole move for one bad waypoint
        move = _move(*nxt, REFUSED_MOVE_MM if avoid else MAX_MOVE_MM)
        return _with_arm({"action": "gripper.move_world", **move}, arm_name, dual)
    if kind == "dgo":
        moves = {
            name: _next_axis(np.array(target, float), obs.arms[name].gc, step[3])
            for name, target in (("left", step[1]), ("right", step[2]))
        }
        if all(m is not None for m in moves.values()):
            return {
                "action": "dual_gripper.move_world",
                **{name: _move(*m) for name, m in moves.items() if m is not None},
            }
        for name, m in moves.items():  # one arm is there: the other moves alone
            if m is not None:
                return {"action": "gripper.move_world", **_move(*m), "arm": name}
        return None
    if kind in ("open", "close"):
        assert arm is not None
        if arm.is_open == (kind == "open"):
            return None
        return _with_arm({"action": f"gripper.{kind}"}, arm_name, dual)
    if kind in ("dopen", "dclose"):
        want_open = kind == "dopen"
        if all(a.is_open == want_open for a in obs.arms.values()):
            return None
        return {"action": f"dual_gripper.{kind[1:]}"}
    raise ValueError(f"unknown step {step!r}")


def decide(obs: Observation, family: str) -> Decision:
    """(action or None for stop, a reason, the memo to carry) for this observation."""
    memo: dict[str, Any] = dict(obs.memo) if obs.memo.get("f") == family else {"f": family}
    plan: list[Step] = memo.get("plan") or families.start_plan(family)
    i = int(memo.get("i", 0))
    topdown = (
        obs.passive or g.view_centre({n: a.gc for n, a in obs.arms.items()}, obs.view) is not None
    )
    if obs.image is None or not looks_like_scene(decode(obs.image), topdown):
        # every view of these scenes shows the table; an image that does not (noise, a broken
        # render) is no ground for any action: look again (active), then give up
        blind = int(memo.get("blind", 0)) + 1
        if blind > MAX_LOOKS or obs.passive:
            return None, "the images do not show the scene", memo
        memo.update(plan=plan, i=i, blind=blind, last=None)
        return {"action": "camera.view_topdown"}, "image unreadable: look again", memo
    memo.pop("blind", None)
    last = memo.get("last")
    for _ in range(len(plan) + 4):
        if i >= len(plan):
            return None, "plan finished", {**memo, "plan": plan, "i": i}
        step = plan[i]
        kind, arm = split_kind(step)
        fails = int(memo.get("fails", 0))
        planner_failed = obs.arms.get(arm) is not None and obs.arms[arm].last_planner is False
        if last == [step[0], i] and (planner_failed or _stuck(kind, arm, obs, memo)):
            fails += 1
        if fails >= MAX_PLANNER_FAILS and kind != "retry":
            # the planner cannot do this step from here: start over from the parked pose
            plan, i, last = [["retry"]], 0, None
            memo.pop("fails", None)
            continue
        memo["fails"] = fails
        if kind == "look":
            if obs.passive:  # the five views come with every observation
                i += 1
                continue
            memo.update(plan=plan, i=i + 1, last=["look", i])
            view = step[1] if len(step) > 1 else "topdown"
            return {"action": f"camera.view_{view}"}, f"look: {view}", memo
        if kind == "see":
            return _see(obs, family, plan, i, memo)
        if kind == "hold":
            side = obs.view_image("side") if obs.passive else obs.image
            seen = (obs.passive or obs.view == "side") and side is not None
            if seen and not grasp_check.in_hand(decode(side), obs.arms[arm].gc):  # type: ignore[arg-type]
                # nothing between the fingers: open and start again from a new look
                plan, i, last = [["open"], *step[1]], 0, None
                continue
            i += 1
            continue
        if kind == "retry":
            tries = int(memo.get("try", 0)) + 1
            if tries >= MAX_TRIES:
                return None, "the task did not end after every try", memo
            plan, i, memo = families.start_plan(family), 0, {"f": family, "try": tries}
            continue
        if kind == "stop":
            return None, str(step[1]) if len(step) > 1 else "stop step", memo
        if kind == "turn" and arm in obs.arms:
            # a turn about the vertical by step[1] deg from wherever the gripper is now: fixed
            # as an absolute heading when first reached, so later decisions steer to it
            target = g.heading_deg(obs.arms[arm].ry) + float(step[1])
            plan = [
                *plan[:i],
                [f"yaw:{arm}", round(g.wrap(target, 360.0), 1), 360.0],
                *plan[i + 1 :],
            ]
            continue
        if kind in ("open", "close", "dopen", "dclose") and last == [step[0], i]:
            out = None  # an aperture command is sent once per step
        else:
            refused = last == [step[0], i] and planner_failed
            out = _step_action(obs, step, kind, arm, memo.get("axis") if refused else None)
        if out is not None:
            memo.update(plan=plan, i=i, last=[step[0], i], at=_gcs(obs), axis=out.get("axis"))
            return out, f"step {i}: {step[0]}", memo
        i += 1
        memo.pop("fails", None)
        last = None
    return None, "no progress", memo


def _see(obs: Observation, family: str, plan: list[Step], i: int, memo: dict[str, Any]) -> Decision:
    scene = None
    centre = g.view_centre({n: a.gc for n, a in obs.arms.items()}, obs.view)
    if obs.image is not None and centre is not None:
        hsv = decode(obs.image)
        cam = g.topdown_camera(tuple(centre), hsv.shape[1], hsv.shape[0])  # type: ignore[arg-type]
        gcs = {n: a.gc for n, a in obs.arms.items()}
        scene = families.locate(family, hsv, cam, gcs, memo)
    if scene is None:
        looks = int(memo.get("looks", 0)) + 1
        if looks > MAX_LOOKS:
            return None, "the objects are not visible in the topdown view", memo
        memo.update(plan=families.look_again(family, looks), i=0, looks=looks, last=None)
        return decide(dataclasses.replace(obs, memo=memo), family)
    rest = families.manipulation_plan(family, scene, memo)
    if rest is None:
        return None, f"no plan for {family}", memo
    seen = {k: [g.r4(v.x), g.r4(v.y), round(v.heading, 1)] for k, v in scene.items()}
    memo = {k: v for k, v in memo.items() if k != "looks"}
    memo.update(plan=rest, i=0, seen=seen, last=None)
    return decide(dataclasses.replace(obs, memo=memo), family)
