"""The observation sent at each decision: its text, and the user turn that carries it.

The text holds exactly the fields of `visibility.OBSERVATION_FIELDS` (spec FACTS.md,
"Observation sent each decision") and nothing else:

    Step 3 of 50 (48 left, this one included).
    Instruction: Pick up the red cube and lift it off the table.
    Current view: center_high
    Robot state (world frame: positions in metres, angles in degrees, quaternion w x y z):
    ```json
    {"right": {"is_open": true, "finger_center_xyz": [...], ..., "last_planner_success": true}}
    ```
    Executed actions (2):
    1. move_world z-30mm
    2. camera.view_topdown
    Demonstration summary: ...
    Available actions:
    {"action": "gripper.move_world", ...}
    ...

The turn puts the text first and the image after it; in the passive protocol the five images
follow in the fixed order of `PASSIVE_VIEWS` with no text between or beside them (the order is
the model's only cue to which view is which).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from vabench.agent.visibility import OBSERVATION_FIELDS, VisibilityError, filter_proprio
from vabench.llm_pool.messages import Image, Turn
from vabench.render.camera import VIEWS

PASSIVE_VIEWS: tuple[str, ...] = VIEWS
"""The passive protocol's views, in the order their images follow the text."""
PASSIVE_VIEW_NAME = "the five fixed views, images in the order " + ", ".join(PASSIVE_VIEWS)
"""What the "Current view" line says in the passive protocol (text above the images, never a
label beside one)."""
INITIAL_VIEW = "center_high"
"""The head camera: the active protocol's view after reset."""


@dataclass(frozen=True)
class ActionFeedback:
    """Outcome of the previous environment action; None before the first one."""

    valid: bool | None = None
    planner_success: bool | None = None


def build_observation(
    *,
    step: int,
    step_budget: int,
    instruction: str,
    view: str,
    proprio: Mapping[str, Mapping[str, Any]],
    arms: Sequence[str],
    feedback: ActionFeedback,
    executed_actions: Sequence[str],
    demonstration_summary: str | Mapping[str, Any] | None,
    available_actions: Sequence[str],
) -> dict[str, Any]:
    """The observation as a dict whose keys are exactly `OBSERVATION_FIELDS`.

    `step` is the 1-based index of the environment step about to be chosen (so `step - 1`
    steps are used); `proprio` is `sim_mjx.layout.proprio_fields(...)` of the episode's slot,
    filtered by `visibility.filter_proprio` (an extra key raises `VisibilityError`); the
    feedback flags are added to every arm (the simulator reports them per episode).
    """
    if not 1 <= step <= step_budget:
        raise VisibilityError("step", f"must be in [1, {step_budget}], got {step}")
    robot = filter_proprio(proprio, arms)
    for fields in robot.values():
        fields["last_action_valid"] = feedback.valid
        fields["last_planner_success"] = feedback.planner_success
    summary = demonstration_summary
    if isinstance(summary, Mapping):
        summary = dict(summary)
    observation = {
        "step": step,
        "step_budget": step_budget,
        "instruction": instruction,
        "view": view,
        "robot": robot,
        "executed_actions": [str(a) for a in executed_actions],
        "demonstration_summary": summary,
        "available_actions": [str(a) for a in available_actions],
    }
    assert tuple(observation) == OBSERVATION_FIELDS  # one list of fields, in visibility.py
    return observation


def _robot_json(robot: Mapping[str, Any]) -> str:
    """One line per arm field: compact, stable, and short enough to repeat every step."""
    lines = []
    for i, (arm, fields) in enumerate(robot.items()):
        lines.append(f"  {json.dumps(arm)}: {{")
        items = list(fields.items())
        for j, (key, value) in enumerate(items):
            comma = "," if j < len(items) - 1 else ""
            lines.append(f"    {json.dumps(key)}: {json.dumps(value)}{comma}")
        lines.append("  }" + ("," if i < len(robot) - 1 else ""))
    return "{\n" + "\n".join(lines) + "\n}"


def render_observation(observation: Mapping[str, Any]) -> str:
    """The text of an observation made by `build_observation` (see the module docstring)."""
    step, budget = observation["step"], observation["step_budget"]
    executed = observation["executed_actions"]
    summary = observation["demonstration_summary"]
    if summary is None:
        summary_text = " none"
    elif isinstance(summary, str):
        summary_text = f" {summary}"
    else:
        summary_text = "\n```json\n" + json.dumps(summary, indent=1) + "\n```"
    lines = [
        f"Step {step} of {budget} ({budget - step + 1} left, this one included).",
        f"Instruction: {observation['instruction']}",
        f"Current view: {observation['view']}",
        "Robot state (world frame: positions in metres, angles in degrees, quaternion w x y z):",
        "```json",
        _robot_json(observation["robot"]),
        "```",
        f"Executed actions ({len(executed)}):" if executed else "Executed actions: none",
        *(f"{i}. {label}" for i, label in enumerate(executed, 1)),
        f"Demonstration summary:{summary_text}",
        "Available actions:",
        *observation["available_actions"],
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
    """The text of a repair turn: what was wrong, then the current observation again."""
    return (
        f"Your previous reply was not accepted: {error}\n"
        "Reply again with one valid JSON object. The current observation follows.\n\n"
        f"{observation}"
    )
