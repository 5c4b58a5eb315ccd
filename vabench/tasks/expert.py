"""Experts: scripted solvers that read evaluator-only state and act only through the model's
JSON actions (FACTS.md "Model-facing protocol").

A family's `Task.expert(sample, ctx)` is a generator: it yields one action dict at a time and,
when resumed, finds the state after that action in `ctx.view` (object poses, gripper poses,
last action result). The primitives below are generators too (`yield from ctx.move_to(...)`):
closed-loop, so an object nudged by the fingers is re-read before the next move, and bounded, so
a stuck expert ends instead of spending the budget. A seed is verified when its expert succeeds
through the batch: solvable through the model's own interface, not through privileged control.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from vabench.sim_mjx.interface import ActionResult

Action = dict[str, Any]
Target = np.ndarray | Callable[["View"], np.ndarray]

MOVE_MAX_MM = 100.0
ROTATE_MAX_DEG = 90.0
MIN_MM = 1.0  # the interface's smallest move and rotation
MIN_DEG = 1.0


@dataclass
class ArmView:
    gc: np.ndarray  # (3,) finger midpoint
    rot: np.ndarray  # (3, 3) columns rx (approach), ry (closing), rz (palm side)
    is_open: bool
    fingers: np.ndarray  # (2,) finger openings, m


@dataclass
class View:
    """Evaluator-only state of one slot, as the expert sees it."""

    objects: dict[str, tuple[np.ndarray, np.ndarray]]  # name -> (pos, rotation matrix)
    init: dict[str, np.ndarray]  # name -> position after the reset's settling
    arms: dict[str, ArmView]
    last: ActionResult | None
    step: int

    def pos(self, name: str) -> np.ndarray:
        return self.objects[name][0]

    def mat(self, name: str) -> np.ndarray:
        return self.objects[name][1]


class ExpertFailed(Exception):
    """The expert cannot continue (a planner failure it has no way around, or a stuck loop)."""


def topdown(yaw: float) -> np.ndarray:
    """Gripper axes pointing straight down, fingers closing along (cos yaw, sin yaw, 0)."""
    rx = np.array([0.0, 0.0, -1.0])
    ry = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    return np.stack([rx, ry, np.cross(rx, ry)], axis=1)


def horizontal(approach_yaw: float, closing_up: bool = False) -> np.ndarray:
    """Gripper axes with a horizontal approach at `approach_yaw` (0 = +x) and the fingers
    closing horizontally (default) or vertically."""
    rx = np.array([np.cos(approach_yaw), np.sin(approach_yaw), 0.0])
    if closing_up:
        ry = np.array([0.0, 0.0, 1.0])
    else:
        ry = np.array([-np.sin(approach_yaw), np.cos(approach_yaw), 0.0])
    return np.stack([rx, ry, np.cross(rx, ry)], axis=1)


def rotation_angle_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def nearest(current: np.ndarray, candidates: list[np.ndarray]) -> np.ndarray:
    """The candidate orientation closest (smallest rotation) to `current`."""
    return min(candidates, key=lambda r: rotation_angle_deg(current.T @ r))


def yaw_candidates(object_yaw: float, symmetry_deg: float) -> list[np.ndarray]:
    """Top-down grasps across an object whose grasp is symmetric every `symmetry_deg`."""
    n = round(360.0 / symmetry_deg)
    return [topdown(object_yaw + np.radians(k * symmetry_deg)) for k in range(n)]


def yaw_of(r: np.ndarray) -> float:
    """Heading of an object's local x axis in the world xy plane."""
    return float(np.arctan2(r[1, 0], r[0, 0]))


def _euler_xyz(r: np.ndarray) -> tuple[float, float, float]:
    """Intrinsic x-y-z angles (rad) with r = Rx(a) Ry(b) Rz(c)."""
    b = float(np.arcsin(np.clip(r[0, 2], -1.0, 1.0)))
    a = float(np.arctan2(-r[1, 2], r[2, 2]))
    c = float(np.arctan2(-r[0, 1], r[0, 0]))
    return a, b, c


class ExpertContext:
    """The expert's handle on one episode: the latest view and the action primitives."""

    def __init__(self, arms: tuple[str, ...], view: View):
        self.arms = arms
        self.dual = len(arms) > 1
        self.view = view

    # -- actions ----------------------------------------------------------------------------
    def _with_arm(self, action: Action, arm: str) -> Action:
        return {**action, "arm": arm} if self.dual else action

    def _signed(
        self, arm: str, action: str, axis: str, amount: float, key: str, most: float
    ) -> Action:
        """A move or rotation action: sign and magnitude (capped at `most`, 0.1 precision)."""
        sign = "+" if amount > 0 else "-"
        magnitude = round(min(abs(float(amount)), most), 1)
        return self._with_arm({"action": action, "axis": axis, "sign": sign, key: magnitude}, arm)

    def move(self, arm: str, axis: str, mm: float) -> Action:
        return self._signed(arm, "gripper.move_world", axis, mm, "distance_mm", MOVE_MAX_MM)

    def rotate(self, arm: str, axis: str, deg: float) -> Action:
        return self._signed(arm, "gripper.rotate_local", axis, deg, "angle_deg", ROTATE_MAX_DEG)

    def aperture(self, arm: str, close: bool) -> Action:
        verb = "close" if close else "open"
        return {"action": f"{arm}_gripper.{verb}" if self.dual else f"gripper.{verb}"}

    # -- primitives (generators) ------------------------------------------------------------
    def _check(self, what: str) -> None:
        last = self.view.last
        if last is not None and not (last.valid and last.planner_success):
            raise ExpertFailed(f"{what}: {last.error or 'planner failed'}")

    def grip(self, arm: str, close: bool) -> Iterator[Action]:
        yield self.aperture(arm, close)
        self._check("grip")

    def rotate_to(
        self, arm: str, target: Target, tol_deg: float = 1.0, max_steps: int = 8
    ) -> Iterator[Action]:
        """Rotate the gripper (GC fixed) to the target axes, one local axis at a time."""
        for _ in range(max_steps):
            goal = target(self.view) if callable(target) else target
            rel = self.view.arms[arm].rot.T @ goal
            if rotation_angle_deg(rel) < tol_deg:
                return
            angles = np.degrees(_euler_xyz(rel))
            k = int(np.argmax(np.abs(angles) >= MIN_DEG))
            if abs(angles[k]) < MIN_DEG:
                return
            yield self.rotate(arm, ("rx", "ry", "rz")[k], float(angles[k]))
            self._check("rotate")
        raise ExpertFailed(f"rotate_to: not within {tol_deg} deg after {max_steps} steps")

    def move_to(
        self,
        arm: str,
        target: Target,
        order: str = "xyz",
        tol_mm: float = 1.0,
        max_steps: int = 16,
    ) -> Iterator[Action]:
        """Bring GC to the target one world axis at a time, in `order`."""
        for _ in range(max_steps):
            goal = target(self.view) if callable(target) else target
            err_mm = (np.asarray(goal) - self.view.arms[arm].gc) * 1000.0
            for axis in order:
                e = err_mm["xyz".index(axis)]
                if abs(e) >= max(tol_mm, MIN_MM):
                    yield self.move(arm, axis, float(e))
                    self._check("move")
                    break
            else:
                return
        raise ExpertFailed(f"move_to: not within {tol_mm} mm after {max_steps} steps")

    def dual_move_to(
        self, targets: dict[str, Target], tol_mm: float = 1.0, max_steps: int = 16
    ) -> Iterator[Action]:
        """Move both grippers together (dual_gripper.move_world), one axis pair per action.
        Used while both hold one object: the two sides always move the same axis."""
        for _ in range(max_steps):
            errs = {}
            for arm, target in targets.items():
                goal = target(self.view) if callable(target) else target
                errs[arm] = (np.asarray(goal) - self.view.arms[arm].gc) * 1000.0
            worst = max(range(3), key=lambda i: max(abs(e[i]) for e in errs.values()))
            if max(abs(e[worst]) for e in errs.values()) < max(tol_mm, MIN_MM):
                return
            sides = {}
            for arm, e in errs.items():
                mm = float(np.clip(e[worst], -MOVE_MAX_MM, MOVE_MAX_MM))
                if abs(mm) < MIN_MM:
                    mm = MIN_MM if mm >= 0 else -MIN_MM
                sides[arm] = {
                    "axis": "xyz"[worst],
                    "sign": "+" if mm > 0 else "-",
                    "distance_mm": round(abs(mm), 1),
                }
            yield {"action": "dual_gripper.move_world", **sides}
            self._check("dual move")
        raise ExpertFailed(f"dual_move_to: not within {tol_mm} mm after {max_steps} steps")
