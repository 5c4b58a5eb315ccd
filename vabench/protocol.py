"""Pydantic models of the model-facing decisions (spec FACTS.md, "Model-facing protocol").

This module holds the robot actions, which the simulator executes; camera actions, tools and
stop join it with the agent harness. Validation happens here, outside jit, and every rejection
names the offending field: `parse_robot_action` raises `ActionError(field, message)`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, TypeAdapter, ValidationError

_SIGN_ALIASES = {
    "+": "+",
    "pos": "+",
    "positive": "+",
    "+1": "+",
    "1": "+",
    "-": "-",
    "neg": "-",
    "negative": "-",
    "-1": "-",
}


def _normalise_sign(value: Any) -> Any:
    if isinstance(value, bool):
        return value  # rejected below: a boolean is no sign
    if isinstance(value, int | float) and value in (1, -1):
        return "+" if value > 0 else "-"
    if isinstance(value, str):
        return _SIGN_ALIASES.get(value.strip().lower(), value)
    return value


Sign = Annotated[Literal["+", "-"], BeforeValidator(_normalise_sign)]
Arm = Literal["left", "right"]


class _Decision(BaseModel):
    model_config = ConfigDict(extra="ignore", frozen=True)
    reason: str | None = None


class AxisMove(BaseModel):
    """One side of a synchronized dual translation."""

    model_config = ConfigDict(extra="ignore", frozen=True)
    axis: Literal["x", "y", "z"]
    sign: Sign
    distance_mm: float = Field(ge=1, le=100)


class MoveWorld(_Decision):
    action: Literal["gripper.move_world"]
    axis: Literal["x", "y", "z"]
    sign: Sign
    distance_mm: float = Field(ge=1, le=100)
    arm: Arm | None = None

    def label(self) -> str:
        return f"move_world {self.arm or ''} {self.axis}{self.sign}{self.distance_mm:g}mm".replace(
            "  ", " "
        )


class RotateLocal(_Decision):
    action: Literal["gripper.rotate_local"]
    axis: Literal["rx", "ry", "rz"]
    sign: Sign
    angle_deg: float = Field(ge=1, le=90)
    arm: Arm | None = None

    def label(self) -> str:
        return f"rotate_local {self.arm or ''} {self.axis}{self.sign}{self.angle_deg:g}deg".replace(
            "  ", " "
        )


GripperName = Literal[
    "gripper.open",
    "gripper.close",
    "left_gripper.open",
    "left_gripper.close",
    "right_gripper.open",
    "right_gripper.close",
    "dual_gripper.open",
    "dual_gripper.close",
]


class Aperture(_Decision):
    action: GripperName
    arm: Arm | None = None

    @property
    def opens(self) -> bool:
        return self.action.endswith(".open")

    def label(self) -> str:
        return self.action if self.arm is None else f"{self.action} {self.arm}"


class DualMove(_Decision):
    action: Literal["dual_gripper.move_world"]
    left: AxisMove
    right: AxisMove

    def label(self) -> str:
        def side(m: AxisMove) -> str:
            return f"{m.axis}{m.sign}{m.distance_mm:g}mm"

        return f"dual_move_world left {side(self.left)} right {side(self.right)}"


RobotAction = Annotated[
    MoveWorld | RotateLocal | Aperture | DualMove, Field(discriminator="action")
]
_ROBOT_ACTION = TypeAdapter(RobotAction)


class ActionError(ValueError):
    """A decision that cannot be executed; `field` names the offending field."""

    def __init__(self, field: str, message: str):
        super().__init__(f"invalid action: field '{field}': {message}")
        self.field = field
        self.message = message


def _first_error(err: ValidationError) -> ActionError:
    e = err.errors()[0]
    # The discriminated union puts the action name first in the location; drop it.
    loc = [str(p) for p in e["loc"]]
    if e["type"] in ("union_tag_invalid", "union_tag_not_found"):
        return ActionError("action", e["msg"])
    if len(loc) > 1 and loc[0].startswith(("gripper.", "dual_gripper.", "left_", "right_")):
        loc = loc[1:]
    return ActionError(".".join(loc) or "action", e["msg"])


def parse_robot_action(
    obj: Any, arms: Sequence[str]
) -> MoveWorld | RotateLocal | Aperture | DualMove:
    """Validate one robot action (a dict as decoded from the model's JSON) for a scene whose
    controllable arms are `arms` (("right",) for single-arm tasks, ("left", "right") for dual)."""
    if not isinstance(obj, dict):
        raise ActionError("action", f"expected a JSON object, got {type(obj).__name__}")
    try:
        action = _ROBOT_ACTION.validate_python(obj)
    except ValidationError as err:
        raise _first_error(err) from None
    dual = len(arms) > 1
    if isinstance(action, DualMove) or action.action.startswith(("dual_", "left_", "right_")):
        if not dual:
            raise ActionError(
                "action", f"'{action.action}' needs a dual-arm task; this task uses {list(arms)}"
            )
        if isinstance(action, Aperture) and action.arm is not None:
            raise ActionError("arm", f"'{action.action}' already names its gripper; omit 'arm'")
        return action
    if dual and action.arm is None:
        raise ActionError("arm", "required in dual-arm tasks: 'left' or 'right'")
    if action.arm is not None and action.arm not in arms:
        raise ActionError("arm", f"'{action.arm}' is not an arm of this task; arms: {list(arms)}")
    return action
