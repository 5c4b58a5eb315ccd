"""Robot actions: per-arm world translations, gripper-local rotations, aperture commands and
the synchronized dual translation (FACTS.md, "Model-facing protocol"), and the world rotation
the benchmark's reference harness accepts without advertising it (PROTOCOL_FACTS 3.3).

The simulator uses this part alone: `parse_robot_action(obj, arms)`. Single-arm tasks reject
the `left_`/`right_`/`dual_` actions; dual-arm tasks require "arm" on `gripper.*` actions.
`gripper.rotate_world` is parsed like every other action but named in no list, template or
error message (`UNADVERTISED`), as in the reference.
Signs accept the spellings models write (pos, positive, +1, 1, neg, negative, -1); a boolean
is never a number.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError

from vabench.protocol.errors import DecisionError, decision_error, show, unknown_action
from vabench.protocol.vocabulary import ANGLE_DEG, DISTANCE_MM, DecisionKind

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


def no_bool(value: Any) -> Any:
    """A BeforeValidator: pydantic's lax mode reads true as 1; a boolean distance or frame
    index is a mistake."""
    if isinstance(value, bool):
        raise ValueError(f"must be a number, got {show(value)}")
    return value


Sign = Annotated[Literal["+", "-"], BeforeValidator(_normalise_sign)]
Arm = Literal["left", "right"]
DistanceMm = Annotated[float, BeforeValidator(no_bool), Field(ge=DISTANCE_MM[0], le=DISTANCE_MM[1])]
AngleDeg = Annotated[float, BeforeValidator(no_bool), Field(ge=ANGLE_DEG[0], le=ANGLE_DEG[1])]


class DecisionModel(BaseModel):
    """The base of every decision: immutable, unknown keys ignored, an optional reason."""

    model_config = ConfigDict(extra="ignore", frozen=True)
    reason: str | None = None


class AxisMove(BaseModel):
    """One side of a synchronized dual translation."""

    model_config = ConfigDict(extra="ignore", frozen=True)
    axis: Literal["x", "y", "z"]
    sign: Sign
    distance_mm: DistanceMm


class MoveWorld(DecisionModel):
    kind: ClassVar[DecisionKind] = "robot"
    action: Literal["gripper.move_world"]
    axis: Literal["x", "y", "z"]
    sign: Sign
    distance_mm: DistanceMm
    arm: Arm | None = None

    def label(self) -> str:
        return f"move_world {self.arm or ''} {self.axis}{self.sign}{self.distance_mm:g}mm".replace(
            "  ", " "
        )


class RotateLocal(DecisionModel):
    kind: ClassVar[DecisionKind] = "robot"
    action: Literal["gripper.rotate_local"]
    axis: Literal["rx", "ry", "rz"]
    sign: Sign
    angle_deg: AngleDeg
    arm: Arm | None = None

    def label(self) -> str:
        return f"rotate_local {self.arm or ''} {self.axis}{self.sign}{self.angle_deg:g}deg".replace(
            "  ", " "
        )


class RotateWorld(DecisionModel):
    """A turn about the fixed world axis `axis` through GC, right-handed for "+": the
    reference's unadvertised `gripper.rotate_world`. Executed as the local rotation about the
    gripper-frame axis that points along the world axis at the start, so GC is held and the
    <= 10 deg waypoints and the whole-path refusal are those of `RotateLocal`."""

    kind: ClassVar[DecisionKind] = "robot"
    action: Literal["gripper.rotate_world"]
    axis: Literal["x", "y", "z"]
    sign: Sign
    angle_deg: AngleDeg
    arm: Arm | None = None

    def label(self) -> str:
        return f"rotate_world {self.arm or ''} {self.axis}{self.sign}{self.angle_deg:g}deg".replace(
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


class Aperture(DecisionModel):
    kind: ClassVar[DecisionKind] = "robot"
    action: GripperName
    arm: Arm | None = None

    @property
    def opens(self) -> bool:
        return self.action.endswith(".open")

    def label(self) -> str:
        return self.action if self.arm is None else f"{self.action} {self.arm}"


class DualMove(DecisionModel):
    kind: ClassVar[DecisionKind] = "robot"
    action: Literal["dual_gripper.move_world"]
    left: AxisMove
    right: AxisMove

    def label(self) -> str:
        def side(m: AxisMove) -> str:
            return f"{m.axis}{m.sign}{m.distance_mm:g}mm"

        return f"dual_move_world left {side(self.left)} right {side(self.right)}"


AnyRobotAction = MoveWorld | RotateLocal | RotateWorld | Aperture | DualMove
RobotAction = Annotated[AnyRobotAction, Field(discriminator="action")]

ROBOT_MODELS: dict[str, type[DecisionModel]] = {
    "gripper.move_world": MoveWorld,
    "gripper.rotate_local": RotateLocal,
    "gripper.rotate_world": RotateWorld,
    "gripper.open": Aperture,
    "gripper.close": Aperture,
    "dual_gripper.move_world": DualMove,
    **{
        f"{side}_gripper.{verb}": Aperture
        for side in ("left", "right", "dual")
        for verb in ("open", "close")
    },
}
"""Every robot action name and the model that validates it."""
UNADVERTISED = frozenset({"gripper.rotate_world"})
"""Robot actions accepted but never offered: in no list of valid names and no template (the
reference's world rotation is parsed and executed, never advertised)."""


def dual_only(name: str) -> bool:
    """Whether the robot action `name` exists only in dual-arm tasks."""
    return name.startswith(("dual_", "left_", "right_"))


def robot_action_names(arms: Sequence[str]) -> tuple[str, ...]:
    """The robot action names offered in a scene whose controllable arms are `arms` (the
    unadvertised ones left out)."""
    return tuple(
        n for n in ROBOT_MODELS if n not in UNADVERTISED and (len(arms) > 1 or not dual_only(n))
    )


def parse_robot_action(obj: Any, arms: Sequence[str]) -> AnyRobotAction:
    """Validate one robot action (a dict as decoded from the model's JSON) for a scene whose
    controllable arms are `arms` (("right",) for single-arm tasks, ("left", "right") for dual).

    Dual-arm tasks require "arm" on `gripper.*` actions; single-arm tasks reject the
    `left_`/`right_`/`dual_` actions. Raises `ActionError` (= `DecisionError`)."""
    if not isinstance(obj, dict):
        raise DecisionError("action", f"expected a JSON object, got {type(obj).__name__}")
    name = obj.get("action")
    if name not in ROBOT_MODELS:
        raise unknown_action(name, robot_action_names(arms))
    dual = len(arms) > 1
    if dual_only(name) and not dual:
        raise DecisionError(
            "action", f"'{name}' needs a dual-arm task; this task uses {list(arms)}"
        )
    try:
        action = ROBOT_MODELS[name].model_validate(obj)
    except ValidationError as err:
        raise decision_error(err) from None
    assert isinstance(action, AnyRobotAction)
    if isinstance(action, DualMove) or dual_only(name):
        if isinstance(action, Aperture) and action.arm is not None:
            raise DecisionError("arm", f"'{name}' already names its gripper; omit 'arm'")
        return action
    if dual and action.arm is None:
        raise DecisionError("arm", "required in dual-arm tasks: 'left' or 'right'")
    if action.arm is not None and action.arm not in arms:
        raise DecisionError("arm", f"'{action.arm}' is not an arm of this task; arms: {list(arms)}")
    return action


def robot_forms(arms: Sequence[str]) -> list[str]:
    """One template per robot action valid with `arms`, with its ranges (for the prompt)."""
    arm = ', "arm": "left|right"' if len(arms) > 1 else ""
    (d_lo, d_hi), (a_lo, a_hi) = DISTANCE_MM, ANGLE_DEG
    move = f'"axis": "x|y|z", "sign": "+|-", "distance_mm": {d_lo:g}..{d_hi:g}'
    forms = [
        f'{{"action": "gripper.move_world", {move}{arm}}}',
        f'{{"action": "gripper.rotate_local", "axis": "rx|ry|rz", "sign": "+|-", '
        f'"angle_deg": {a_lo:g}..{a_hi:g}{arm}}}',
        f'{{"action": "gripper.open"{arm}}}',
        f'{{"action": "gripper.close"{arm}}}',
    ]
    if len(arms) > 1:
        forms += [
            f'{{"action": "{n}"}}'
            for n in robot_action_names(arms)
            if dual_only(n) and ROBOT_MODELS[n] is Aperture
        ]
        forms.append(
            f'{{"action": "dual_gripper.move_world", "left": {{{move}}}, "right": {{{move}}}}}'
        )
    return forms
