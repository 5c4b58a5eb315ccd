"""Evidence hints: observations computed from an episode's records that point an annotator at
the steps that matter for a criterion. They are suggestions shown in the viewer only; labels
come from annotators and judges, never from here.

Each hint names the item it bears on, the step, what was seen, and where it comes from:
`visible` hints use only what the model itself saw (its actions, validity, planner results,
its robot state); `evaluator` hints read evaluator-only state (object poses) and are marked so
in the viewer. Each kind of hint is a `HintRule` of `RULES` that names the protocols it applies
to: an episode gets only the hints of its own protocol.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

from vabench.protocol.vocabulary import ObservationProtocol

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


Events = Sequence[dict[str, Any]]


def _robot_steps(events: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    return [e for e in events if e.get("type") == "action"]


def _failed(e: dict[str, Any]) -> bool:
    return not (e.get("valid") and e.get("planner_success"))


def _failures(events: Events) -> list[tuple[dict[str, Any], dict[str, Any] | None]]:
    """Each failed robot action with the robot action after it (None: the last)."""
    actions = _robot_steps(events)
    return [
        (e, actions[i + 1] if i + 1 < len(actions) else None)
        for i, e in enumerate(actions)
        if _failed(e)
    ]


def _failed_actions(events: Events) -> list[Hint]:
    out = []
    for e, _ in _failures(events):
        why = "invalid action" if not e.get("valid") else "planner rejected the motion"
        out.append(Hint("gate_error", e["step"], f"{why}: {e.get('label')}"))
    return out


def _after_failure(events: Events) -> list[Hint]:
    out = []
    for e, later in _failures(events):
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
    return out


def _view_after_failure(events: Events) -> list[Hint]:
    out = []
    for e, later in _failures(events):
        until = later["step"] if later is not None else math.inf
        if any(c.get("type") == "camera" and e["step"] < c["step"] <= until for c in events):
            out.append(Hint("ED", e["step"], "took another view after the failure"))
    return out


def _camera_first(events: Events) -> list[Hint]:
    cameras = [e for e in events if e.get("type") == "camera"]
    actions = _robot_steps(events)
    if not cameras or cameras[0]["step"] >= (actions[0]["step"] if actions else math.inf):
        return []
    label = cameras[0].get("label")
    return [
        Hint("AE", cameras[0]["step"], f"camera action ({label}) before the first robot action")
    ]


def _no_camera(events: Events) -> list[Hint]:
    if any(e.get("type") == "camera" for e in events):
        return []
    return [Hint("AE", 0, "no camera action in the whole episode")]


def _rejections(events: Events) -> list[Hint]:
    return [
        Hint("MS", e["step"], f"reply rejected by the protocol ({e.get('field')})")
        for e in events
        if e.get("type") == "rejection"
    ]


def _geometry_checks(events: Events) -> list[Hint]:
    return [
        Hint("FG", e["step"], "checked the robot's geometry (geometry.verify)")
        for e in events
        if e.get("type") == "tool" and e.get("label", "").startswith("geometry.verify")
    ]


def _clipped(events: Events) -> list[Hint]:
    return [
        Hint("SR", e["step"], "target clipped to the workspace bounds")
        for e in _robot_steps(events)
        if any((e.get("clipped") or {}).values())
    ]


def _gc(action: dict[str, Any]) -> list[tuple[float, ...]]:
    return [tuple(p["finger_center_xyz"]) for p in (action.get("proprio") or {}).values()]


def _object_hints(events: Events) -> list[Hint]:
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


@dataclass(frozen=True)
class HintRule:
    """One kind of hint and the protocols whose episodes it can speak about: a hint about
    camera actions says nothing of a passive episode, whose model cannot move the camera (it
    gets the five fixed views every step). Tracks need no entry of their own: a track is a
    protocol and a task suite (`vabench.config.BUILTIN_TRACKS`), and no hint depends on the
    suite."""

    name: str
    protocols: frozenset[ObservationProtocol]
    find: Callable[[Events], list[Hint]]


BOTH: frozenset[ObservationProtocol] = frozenset(("active", "passive"))
ACTIVE_ONLY: frozenset[ObservationProtocol] = frozenset(("active",))

RULES: tuple[HintRule, ...] = (
    HintRule("failed_action", BOTH, _failed_actions),
    HintRule("after_failure", BOTH, _after_failure),
    HintRule("view_after_failure", ACTIVE_ONLY, _view_after_failure),
    HintRule("camera_first", ACTIVE_ONLY, _camera_first),
    HintRule("no_camera", ACTIVE_ONLY, _no_camera),
    HintRule("rejection", BOTH, _rejections),
    HintRule("geometry_check", BOTH, _geometry_checks),
    HintRule("clipped", BOTH, _clipped),
    HintRule("object_poses", BOTH, _object_hints),
)
"""Every hint, with the protocols it applies to: the one place that says which hint an
episode of a protocol can get."""


def hints(events: Sequence[dict[str, Any]], protocol: ObservationProtocol) -> list[Hint]:
    """Every hint of one episode of `protocol` (its result's), in step order."""
    out: list[Hint] = []
    for rule in RULES:
        if protocol in rule.protocols:
            out += rule.find(events)
    return sorted(out, key=lambda h: (h.step, h.item))
