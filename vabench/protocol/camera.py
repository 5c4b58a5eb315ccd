"""Camera actions: they move the observation camera, never the robot (active protocol only).

The names are the camera model's (`vabench.render.camera` implements them); here they are
parsed. The chain of at most `MAX_CAMERA_CHAIN` camera actions in a row is an instruction of
the system prompt, never a rejection (the paper's "agent instruction"; the reference enforces
none); `camera_chain_length` counts it for the records.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

from pydantic import ValidationError

from vabench.protocol.context import DecisionContext
from vabench.protocol.errors import DecisionError, decision_error, unknown_action
from vabench.protocol.robot import DecisionModel, robot_action_names
from vabench.protocol.vocabulary import (
    ALL_CAMERA_NAMES,
    CAMERA_INCREMENTS,
    CAMERA_TARGETS,
    CAMERA_VIEWS,
    DecisionKind,
    ObservationProtocol,
    camera_action_names,
)


class CameraAction(DecisionModel):
    """A camera action: moves the observation camera, never the robot. No parameters."""

    kind: ClassVar[DecisionKind] = "camera"
    action: str

    def _target_and_view(self) -> tuple[str | None, str | None]:
        rest = self.action.removeprefix("camera.view_")
        if rest in CAMERA_VIEWS:
            return None, rest
        target, _, view = rest.partition("_")
        return (target, view) if target in CAMERA_TARGETS and view in CAMERA_VIEWS else (None, None)

    @property
    def view(self) -> str | None:
        """The semantic view ("topdown", ...), None for an increment."""
        return self._target_and_view()[1]

    @property
    def target(self) -> str | None:
        """The explicit target of a dual-arm view ("left", "right" or "both"); None otherwise
        (the generic views follow the only arm in single-arm tasks, the midpoint in dual-arm)."""
        return self._target_and_view()[0]

    @property
    def increment(self) -> str | None:
        """The increment ("move_left", "zoom_in", ...); None for a view."""
        name = self.action.removeprefix("camera.")
        return name if name in CAMERA_INCREMENTS else None

    def label(self) -> str:
        return self.action


def action_names(arms: Sequence[str], protocol: ObservationProtocol) -> tuple[str, ...]:
    """Robot and (active protocol only) camera action names valid in an episode."""
    cameras = camera_action_names(arms) if protocol == "active" else ()
    return (*robot_action_names(arms), *cameras)


def parse_camera_action(obj: dict[str, Any], ctx: DecisionContext) -> CameraAction:
    """Validate a decision whose "action" starts with "camera."."""
    name = obj["action"]
    if ctx.protocol == "passive":
        raise DecisionError(
            "action",
            "camera actions are not available in the passive protocol; "
            "the five views are supplied every observation",
        )
    valid = camera_action_names(ctx.arms)
    if name not in valid:
        if name in ALL_CAMERA_NAMES:
            raise DecisionError(
                "action", f"'{name}' needs a dual-arm task; this task uses {list(ctx.arms)}"
            )
        raise unknown_action(name, action_names(ctx.arms, ctx.protocol))
    if "arm" in obj:
        raise DecisionError(
            "arm",
            "camera actions take no parameters; to aim at one arm use "
            "camera.view_left_<view> or camera.view_right_<view>"
            if len(ctx.arms) > 1
            else "camera actions take no parameters",
        )
    try:
        return CameraAction.model_validate(obj)
    except ValidationError as err:
        raise decision_error(err) from None


def camera_chain_length(kinds: Sequence[str]) -> int:
    """Camera actions executed since the last robot action.

    `kinds`: the kinds of the episode's decisions so far, oldest first ("robot", "camera",
    "tool", "stop", or anything the engine records, e.g. "rejected"). Only "robot" resets the
    chain; every kind other than "camera" and "robot" neither breaks nor extends it, so a tool
    call or a rejected reply cannot be used to launder a long camera chain.
    """
    count = 0
    for kind in reversed(kinds):
        if kind == "robot":
            break
        count += kind == "camera"
    return count
