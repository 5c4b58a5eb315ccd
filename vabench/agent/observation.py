"""The observation sent at each decision: its text, and the user turn that carries it.

The text holds exactly the fields of `visibility.OBSERVATION_FIELDS` and nothing else, in the
reference's order (spec PROTOCOL_FACTS.md 2.1-2.5; docs/PROTOCOL.md):

    Observation step: 3
    Task instruction: Pick up the red cube and lift it off the table.
    Gripper state: {"is_open": true, "is_closed": false, "finger_center_xyz": [...], ...}
    Robot self-geometry (robot state only: not object positions, not proof of contact):
    {"control_eepose_xyz": [...], ..., "topdown_posture_ok_45deg": true}
    Executed actions: ["move_world z-30mm", "camera.view_topdown"]
    Historical image steps available: [1, 2]
    Available actions (gripper moves and rotations in the numeric JSON forms):
    gripper.open
    ...
    Reply with exactly one JSON command.
    Demonstration summary (kept as additive experience unless the images disprove it):
    ...

No step budget and no view name are shown: the model knows its view from its own camera
actions. The self-geometry block is derived here from the visible robot state alone
(`self_geometry`). The history line appears only where `camera.history` is offered.

The turn puts the text first and the image after it; in the passive protocol the five images
follow in the fixed order of `PASSIVE_VIEWS` with no text between or beside them (the order is
the model's only cue to which view is which).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from vabench.agent.visibility import OBSERVATION_FIELDS, VisibilityError, filter_proprio
from vabench.llm_pool.messages import Image, Turn
from vabench.render.camera import VIEWS

PASSIVE_VIEWS: tuple[str, ...] = VIEWS
"""The passive protocol's views, in the order their images follow the text."""
PASSIVE_VIEW_NAME = "the five fixed views, images in the order " + ", ".join(PASSIVE_VIEWS)
"""What the records call the passive bundle's view (never shown to the model)."""
INITIAL_VIEW = "center_high"
"""The head camera: the active protocol's view after reset."""
SELF_GEOMETRY_HEADER = (
    "Robot self-geometry (robot state only: not object positions, not proof of contact):"
)
GRIPPER_STATE_FIELDS: tuple[str, ...] = (
    "is_open",
    "is_closed",
    "finger_center_xyz",
    "control_eepose_xyz",
    "control_eepose_rpy_deg",
    "control_eepose_quat",
)
"""One arm's fields of the gripper state line, in order (the axes are in the self-geometry)."""
TOPDOWN_LIMITS_DEG = (30, 45)
"""The top-down posture flags: GC direction within this angle of the table's downward normal."""
_AXIS_DIRECTIONS = {
    "+X": (1.0, 0.0, 0.0),
    "-X": (-1.0, 0.0, 0.0),
    "+Y": (0.0, 1.0, 0.0),
    "-Y": (0.0, -1.0, 0.0),
    "+Z": (0.0, 0.0, 1.0),
    "-Z": (0.0, 0.0, -1.0),
}


@dataclass(frozen=True)
class ActionFeedback:
    """Outcome of the previous environment action; both true before the first one and after a
    camera action (nothing was refused)."""

    valid: bool = True
    planner_success: bool = True


def _angle_deg(u: Sequence[float], v: Sequence[float]) -> float:
    dot = sum(a * b for a, b in zip(u, v, strict=True))
    return math.degrees(math.acos(max(-1.0, min(1.0, dot))))


def self_geometry(fields: Mapping[str, Any]) -> dict[str, Any]:
    """The self-geometry of one arm from its visible fields (`filter_proprio`'s): where GC lies
    from the control point, how that direction sits against the world axes and the table's
    downward normal, and whether the posture is top-down within 30 and 45 deg. A GC closer
    than 1 um to the control point falls back on the approach axis rx."""
    ee, gc = fields["control_eepose_xyz"], fields["finger_center_xyz"]
    offset = [g - e for g, e in zip(gc, ee, strict=True)]
    length = math.sqrt(sum(c * c for c in offset))
    if length >= 1e-6:
        direction, source = [c / length for c in offset], "finger_center_minus_eepose"
    else:
        direction, source = list(fields["local_axes_world"]["rx"]), "local_rx_fallback"
    angles = {
        name: round(_angle_deg(direction, axis), 1) for name, axis in _AXIS_DIRECTIONS.items()
    }
    down = angles["-Z"]
    geometry: dict[str, Any] = {
        "control_eepose_xyz": [round(c, 4) for c in ee],
        "finger_center_xyz": [round(c, 4) for c in gc],
        "control_eepose_quat_wxyz": [round(c, 5) for c in fields["control_eepose_quat"]],
        "control_eepose_rpy_deg": [round(c, 2) for c in fields["control_eepose_rpy_deg"]],
        "local_axes_world": {
            k: [round(c, 4) for c in v] for k, v in fields["local_axes_world"].items()
        },
        "grip_center_direction_world": [round(c, 4) for c in direction],
        "grip_center_direction_source": source,
        "grip_center_length_m": round(length, 4),
        "grip_center_angle_to_world_axes_deg": angles,
        "grip_center_angle_to_table_down_deg": down,
    }
    for limit in TOPDOWN_LIMITS_DEG:
        geometry[f"topdown_posture_ok_{limit}deg"] = down <= limit
    return geometry


def _gripper_state(fields: Mapping[str, Any]) -> dict[str, Any]:
    state = {"is_closed": not fields["is_open"], **fields}
    return {k: state[k] for k in GRIPPER_STATE_FIELDS}


TYPICAL_PROPRIO = {
    "is_open": True,
    "finger_center_xyz": [0.1234, -0.1234, 0.9123],
    "control_eepose_xyz": [0.1234, -0.1234, 1.0123],
    "control_eepose_rpy_deg": [-179.12, 12.34, 90.12],
    "control_eepose_quat": [0.1234, -0.7012, 0.7012, 0.0123],
    "local_axes_world": {
        "rx": [0.0123, -0.0123, -0.9998],
        "ry": [0.9998, 0.0123, 0.0123],
        "rz": [-0.0123, 0.9998, -0.0123],
    },
}
"""One arm's state as an observation shows it, with realistic digits: what the dry run's
estimates and the endpoint check's probe put in an observation they build without a scene."""


def build_observation(
    *,
    step: int,
    step_budget: int,
    instruction: str,
    proprio: Mapping[str, Mapping[str, Any]],
    arms: Sequence[str],
    feedback: ActionFeedback,
    executed_actions: Sequence[str],
    demonstration_summary: str | Mapping[str, Any] | None,
    available_actions: Sequence[str],
    history_steps: Sequence[int] | None = None,
) -> dict[str, Any]:
    """The observation as a dict whose keys are exactly `OBSERVATION_FIELDS`.

    `step` is the 1-based index of the environment step about to be chosen (so `step - 1`
    steps are used; `step_budget` only bounds it: the budget is never shown); `proprio` is
    `sim_mjx.layout.proprio_fields(...)` of the episode's slot, filtered by
    `visibility.filter_proprio` (an extra key raises `VisibilityError`). The gripper state has
    the reference's shape: one arm's fields with `active_arm`, or both arms' under `left` and
    `right` with `active_arm: "both"`; the feedback flags follow once, for the episode.
    `history_steps`: the earlier observation steps `camera.history` can show (None: the tool
    is not offered, and the line is left out).
    """
    if not 1 <= step <= step_budget:
        raise VisibilityError("step", f"must be in [1, {step_budget}], got {step}")
    robot = filter_proprio(proprio, arms)
    flags = {
        "last_action_valid": feedback.valid,
        "last_planner_success": feedback.planner_success,
    }
    if len(arms) == 1:
        (arm,) = arms
        gripper = {**_gripper_state(robot[arm]), "active_arm": arm, **flags}
        geometry = self_geometry(robot[arm])
    else:
        gripper = {"active_arm": "both", **{a: _gripper_state(robot[a]) for a in arms}, **flags}
        geometry = {"active_arm": "both", **{a: self_geometry(robot[a]) for a in arms}}
    summary = demonstration_summary
    if isinstance(summary, Mapping):
        summary = dict(summary)
    observation = {
        "step": step,
        "instruction": instruction,
        "gripper_state": gripper,
        "self_geometry": geometry,
        "executed_actions": [str(a) for a in executed_actions],
        "history_steps": None if history_steps is None else [int(s) for s in history_steps],
        "available_actions": [str(a) for a in available_actions],
        "demonstration_summary": summary,
    }
    assert tuple(observation) == OBSERVATION_FIELDS  # one list of fields, in visibility.py
    return observation


def render_observation(observation: Mapping[str, Any]) -> str:
    """The text of an observation made by `build_observation` (see the module docstring)."""
    history = observation["history_steps"]
    summary = observation["demonstration_summary"]
    lines = [
        f"Observation step: {observation['step']}",
        f"Task instruction: {observation['instruction']}",
        f"Gripper state: {json.dumps(observation['gripper_state'])}",
        SELF_GEOMETRY_HEADER,
        json.dumps(observation["self_geometry"]),
        f"Executed actions: {json.dumps(observation['executed_actions'])}",
    ]
    if history is not None:
        lines.append(
            f"Historical image steps available: {json.dumps(history) if history else 'none'}"
        )
    lines += [
        "",
        "Available decisions (one JSON form a line; numbers within the ranges shown):",
        *observation["available_actions"],
        "",
        "Reply with exactly one JSON command.",
    ]
    if summary is not None:
        shown = (
            summary
            if isinstance(summary, str)
            else json.dumps(summary, indent=2, ensure_ascii=False)
        )
        lines += [
            "",
            "Demonstration summary (saved for this run; keep it as additive experience unless "
            "later images disprove an item):",
            shown,
        ]
    return "\n".join(lines)


def observation_text(**fields: Any) -> str:
    """`render_observation(build_observation(**fields))`."""
    return render_observation(build_observation(**fields))


def passive_bundle(images: Mapping[str, Image]) -> tuple[Image, ...]:
    """The five passive images in `PASSIVE_VIEWS` order; raises naming a missing or extra view."""
    extra = [v for v in images if v not in PASSIVE_VIEWS]
    if extra:
        raise VisibilityError(f"images.{extra[0]}", f"not a passive view; views: {PASSIVE_VIEWS}")
    missing = [v for v in PASSIVE_VIEWS if v not in images]
    if missing:
        raise VisibilityError(f"images.{missing[0]}", "missing from the five-view bundle")
    return tuple(images[v] for v in PASSIVE_VIEWS)


def observation_turn(text: str, images: Image | Mapping[str, Image]) -> Turn:
    """The user turn of an observation: the text, then one image (active) or the five passive
    images in fixed order with nothing between them."""
    bundle = (images,) if isinstance(images, Image) else passive_bundle(images)
    return Turn.user(text, *bundle)


def repair_text(error: str, observation: str) -> str:
    """The text of a repair turn (PROTOCOL_FACTS 3.5): the current observation's text again,
    what was wrong with the reply, and a request for one corrected command."""
    return (
        f"{observation}\n\n"
        f"Your previous reply was not accepted: {error}\n"
        "Reply with one corrected command: one valid JSON object."
    )
