"""Evidence hints: observations computed from an episode's records that point an annotator at
the steps that matter for a criterion. They are suggestions shown in the viewer only; labels
come from annotators and judges, never from here.

Each hint names the item it bears on, the step, what was seen, and where it comes from:
`visible` hints use only what the model itself saw (its actions, validity, planner results,
its robot state); `evaluator` hints read evaluator-only state (object poses) and are marked so
in the viewer.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

DROP_M = 0.02
"""An object that rose this far above its resting height and came back down was dropped."""
NEAR_M = 0.04
"""A gripper closing farther than this from every object grasps nothing (a candidate miss)."""


@dataclass(frozen=True)
class Hint:
    item: str
    step: int
    text: str
    source: str = "visible"
    """visible | evaluator"""

    def record(self) -> dict[str, Any]:
        return asdict(self)


def _robot_steps(events: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    return [e for e in events if e.get("type") == "action"]


def _failed(e: dict[str, Any]) -> bool:
    return not (e.get("valid") and e.get("planner_success"))


def hints(events: Sequence[dict[str, Any]]) -> list[Hint]:
    """Every hint of one episode, in step order."""
    out: list[Hint] = []
    actions = _robot_steps(events)
    cameras = [e for e in events if e.get("type") == "camera"]
    out += _failure_hints(actions, events)
    if cameras:
        first_cam = cameras[0]["step"]
        first_robot = actions[0]["step"] if actions else math.inf
        if first_cam < first_robot:
            out.append(
                Hint(
                    "AE",
                    first_cam,
                    f"camera action ({cameras[0].get('label')}) before the first robot action",
                )
            )
    else:
        out.append(Hint("AE", 0, "no camera action in the whole episode"))
    for e in events:
        if e.get("type") == "rejection":
            out.append(Hint("MS", e["step"], f"reply rejected by the protocol ({e.get('field')})"))
        elif e.get("type") == "tool" and e.get("label", "").startswith("geometry.verify"):
            out.append(Hint("FG", e["step"], "checked the robot's geometry (geometry.verify)"))
        elif e.get("type") == "action" and any((e.get("clipped") or {}).values()):
            out.append(Hint("SR", e["step"], "target clipped to the workspace bounds"))
    out += _object_hints(events)
    return sorted(out, key=lambda h: (h.step, h.item))


def _failure_hints(actions: list[dict[str, Any]], events: Sequence[dict[str, Any]]) -> list[Hint]:
    out = []
    for i, e in enumerate(actions):
        if not _failed(e):
            continue
        why = "invalid action" if not e.get("valid") else "planner rejected the motion"
        out.append(Hint("gate_error", e["step"], f"{why}: {e.get('label')}"))
        later = actions[i + 1] if i + 1 < len(actions) else None
        looked = any(
            c.get("type") == "camera" and e["step"] < c["step"] <= (later or {"step": 1e9})["step"]
            for c in events
        )
        if later is None:
            out.append(Hint("PF", e["step"], "no robot action after the failure"))
        elif later.get("label") == e.get("label"):
            out.append(Hint("PF", later["step"], "repeated the failed action unchanged"))
        else:
            out.append(
                Hint(
                    "PF",
                    later["step"],
                    f"changed the action after the failure "
                    f"({e.get('label')} -> {later.get('label')})",
                )
            )
        if looked:
            out.append(Hint("ED", e["step"], "took another view after the failure"))
    return out


def _gc(action: dict[str, Any]) -> list[tuple[float, ...]]:
    return [tuple(p["finger_center_xyz"]) for p in (action.get("proprio") or {}).values()]


def _object_hints(events: Sequence[dict[str, Any]]) -> list[Hint]:
    """Drops and closes far from every object, from the evaluator-only object poses."""
    reset = next((e for e in events if e.get("type") == "reset" and e.get("objects")), None)
    if reset is None:
        return []
    rest = {n: p["pos"][2] for n, p in reset["objects"].items()}
    peak = dict(rest)
    out: list[Hint] = []
    for e in _robot_steps(events):
        objects = e.get("objects") or {}
        for name, pose in objects.items():
            z = pose["pos"][2]
            if name in peak and peak[name] - rest[name] >= DROP_M and z - rest[name] < DROP_M / 2:
                out.append(
                    Hint(
                        "gate_error",
                        e["step"],
                        f"{name} fell back after being raised "
                        f"{1000 * (peak[name] - rest[name]):.0f} mm (a drop)",
                        "evaluator",
                    )
                )
                peak[name] = z
            elif name in peak:
                peak[name] = max(peak[name], z)
        if "close" in str(e.get("label")) and objects and e.get("planner_success"):
            gcs = _gc(e)
            nearest = min(
                (math.dist(g, o["pos"]) for g in gcs for o in objects.values()), default=math.inf
            )
            if nearest > NEAR_M:
                out.append(
                    Hint(
                        "gate_error",
                        e["step"],
                        f"gripper closed {1000 * nearest:.0f} mm "
                        "from the nearest object (a candidate miss)",
                        "evaluator",
                    )
                )
    return out
