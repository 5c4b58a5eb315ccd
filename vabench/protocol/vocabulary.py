"""The names and ranges a model may use, with the budgets of a decision; no parsing here.

Everything that lists, validates or explains decisions reads these, so the prompt's templates,
the validators and the repair messages cannot drift apart.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

MAX_REPAIRS_PER_DECISION = 2
"""Repair attempts per decision for malformed JSON or an invalid decision."""
MAX_TOOL_ROUND_TRIPS = 20
"""Model/tool round trips per environment decision."""
MAX_CAMERA_CHAIN = 5
"""Camera actions allowed in a row; the next one must wait for a robot action."""
MAX_EXPERT_FRAMES = 8
"""Frames one `expert.frame` call may request."""
LEARNING_STAGE_MARK = "There are no robot or camera actions in this stage."
"""A sentence of the learning stage's system prompt, so stand-in policies can tell that stage
from an evaluation episode."""

DISTANCE_MM = (1, 100)
"""The (min, max) of a world translation, millimetres."""
ANGLE_DEG = (1, 90)
"""The (min, max) of a gripper-local rotation, degrees."""

DecisionKind = Literal["robot", "camera", "tool", "stop"]
ObservationProtocol = Literal["active", "passive"]
ARMS = ("left", "right")

CAMERA_VIEWS = ("topdown", "side", "front_side_45", "side_top_45", "oblique_45")
"""The five semantic views, in the fixed order of the passive bundle."""
CAMERA_TARGETS = ("left", "right", "both")
"""Explicit view targets of dual-arm tasks (`camera.view_<target>_<view>`)."""
CAMERA_INCREMENTS = (
    "move_left",
    "move_right",
    "move_up",
    "move_down",
    "zoom_in",
    "zoom_out",
    "yaw_left",
    "yaw_right",
    "pitch_up",
    "pitch_down",
)
"""Camera moves relative to the current view (`camera.<increment>`)."""

BASE_TOOLS = ("geometry.verify", "camera.history")
DEMONSTRATION_TOOLS = ("expert.retrieve", "expert.frame", "expert.learn")
TOOL_NAMES = (*BASE_TOOLS, *DEMONSTRATION_TOOLS)
ToolName = Literal[
    "geometry.verify", "camera.history", "expert.retrieve", "expert.frame", "expert.learn"
]


def available_tools(demonstration: bool) -> tuple[str, ...]:
    """The tools of an episode: the demonstration tools only when a demonstration exists."""
    return TOOL_NAMES if demonstration else BASE_TOOLS


def camera_action_names(arms: Sequence[str]) -> tuple[str, ...]:
    """Every camera action name valid in a scene with `arms` (active protocol only)."""
    views = [f"camera.view_{v}" for v in CAMERA_VIEWS]
    if len(arms) > 1:
        views += [f"camera.view_{t}_{v}" for t in CAMERA_TARGETS for v in CAMERA_VIEWS]
    return (*views, *(f"camera.{i}" for i in CAMERA_INCREMENTS))


ALL_CAMERA_NAMES = camera_action_names(ARMS)
"""Every camera action name of a dual-arm scene (a superset of the single-arm ones)."""
