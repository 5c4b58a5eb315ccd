"""The model-facing decision layer (spec FACTS.md, "Model-facing protocol").

One model reply carries one decision, a JSON object: a robot action (executed by the
simulator), a camera action (moves the observation camera only), a tool call (never advances
the simulator) or a stop. This module turns the reply text into a validated, immutable
decision, or raises `DecisionError(field, message)` whose text is written to be sent back to
the model as repair feedback.

What the episode engine calls:

- `DecisionContext(arms, protocol, tools, camera_chain)`: what this episode allows.
  `available_tools(demonstration)` gives `tools`; `camera_chain_length(kinds)` gives
  `camera_chain` from the kinds of the decisions executed so far.
- `parse_decision(text, ctx) -> Decision`: extraction, dispatch, validation, camera-chain rule.
  `decision_from_object(obj, ctx)` does the same for an already decoded JSON object.
- `decision_label(decision)`: the compact label recorded in events and shown in the history.
- `available_actions(arms, protocol, tools)`: the vocabulary listed in every observation.
- `MAX_REPAIRS_PER_DECISION`, `MAX_TOOL_ROUND_TRIPS`, `MAX_CAMERA_CHAIN`: the budgets.

The simulator uses the robot part alone: `parse_robot_action(obj, arms)`.

Decisions the spec leaves open, made here:

- Reply extraction (`extract_json_object`): a fenced block tagged json wins over bare text;
  with several, the LAST one is taken, because models that think aloud show drafts and
  alternatives first and commit at the end. Untagged fences count only when no json-tagged one
  exists and their body starts with "{"; fences of other languages are ignored. Without a
  fence, the top-level balanced {...} spans of the text are found (braces inside JSON strings
  do not count; an unmatched prose "{" is skipped), and the last one that decodes to an object
  with an "action", "tool" or "stop" key is taken (else the last object). A chosen block that
  does not decode is an error, never a silent fall-back to an earlier draft.
- Dispatch: `"stop": true` first (any other key is ignored), then "tool" (a missing "args"
  means {}), then "action". A non-boolean "stop" is an error rather than a guess.
- Unknown keys are ignored, except "arm" on a camera action, which is rejected with a hint to
  use `camera.view_left_*` / `camera.view_right_*` (ignoring it would silently aim elsewhere).
- `expert.learn` accepts the summary as a non-empty string or a non-empty object (FACTS lists
  structured summary fields); checking those fields belongs to the demonstration tools.
- Camera chain: only a robot action resets it; tool calls, rejected decisions and anything
  else neither break nor extend it (see `camera_chain_length`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError
from pydantic_core import ErrorDetails

from vabench.render import camera as _camera

MAX_REPAIRS_PER_DECISION = 2
"""Repair attempts per decision for malformed JSON or an invalid decision."""
MAX_TOOL_ROUND_TRIPS = 20
"""Model/tool round trips per environment decision."""
MAX_CAMERA_CHAIN = 5
"""Camera actions allowed in a row; the next one must wait for a robot action."""
MAX_EXPERT_FRAMES = 8
LEARNING_STAGE_MARK = "There are no robot or camera actions in this stage."
"""A sentence of the learning stage's system prompt, so stand-in policies can tell that stage
from an evaluation episode."""
"""Frames one `expert.frame` call may request."""

DecisionKind = Literal["robot", "camera", "tool", "stop"]
ObservationProtocol = Literal["active", "passive"]


class DecisionError(ValueError):
    """A reply that cannot be turned into a decision.

    `field` names the offending field ("reply" for the reply as a whole, "args.step" inside a
    tool's arguments, "right.distance_mm" inside a dual move); `message` says what is wrong and
    what is valid. `str(error)` is the repair text for the model; when several fields are wrong
    at once, `others` holds the rest and `str` lists them all, so one repair can fix them all.
    """

    def __init__(self, field: str, message: str, others: Sequence[tuple[str, str]] = ()):
        self.field = field
        self.message = message
        self.others = tuple(others)
        parts = [message if field == REPLY else f"field '{field}': {message}"]
        parts += [f"field '{f}': {m}" for f, m in self.others]
        super().__init__("; ".join(parts))


ActionError = DecisionError
"""The name the simulator side uses; one concept, one class."""

REPLY = "reply"
"""The `DecisionError.field` of problems with the reply as a whole (no JSON, invalid JSON)."""


def _show(value: Any) -> str:
    """A value as the model wrote it (JSON), shortened for repair text."""
    text = json.dumps(value, default=str)
    return text if len(text) <= 60 else text[:57] + "..."


# -- robot actions ---------------------------------------------------------------------------

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


def _no_bool(value: Any) -> Any:
    # pydantic's lax mode reads true as 1; a boolean distance or frame index is a mistake.
    if isinstance(value, bool):
        raise ValueError(f"must be a number, got {_show(value)}")
    return value


Sign = Annotated[Literal["+", "-"], BeforeValidator(_normalise_sign)]
Arm = Literal["left", "right"]
DistanceMm = Annotated[float, BeforeValidator(_no_bool), Field(ge=1, le=100)]
AngleDeg = Annotated[float, BeforeValidator(_no_bool), Field(ge=1, le=90)]
FrameIndex = Annotated[int, BeforeValidator(_no_bool), Field(ge=0)]


class _Decision(BaseModel):
    model_config = ConfigDict(extra="ignore", frozen=True)
    reason: str | None = None


class AxisMove(BaseModel):
    """One side of a synchronized dual translation."""

    model_config = ConfigDict(extra="ignore", frozen=True)
    axis: Literal["x", "y", "z"]
    sign: Sign
    distance_mm: DistanceMm


class MoveWorld(_Decision):
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


class RotateLocal(_Decision):
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
    kind: ClassVar[DecisionKind] = "robot"
    action: GripperName
    arm: Arm | None = None

    @property
    def opens(self) -> bool:
        return self.action.endswith(".open")

    def label(self) -> str:
        return self.action if self.arm is None else f"{self.action} {self.arm}"


class DualMove(_Decision):
    kind: ClassVar[DecisionKind] = "robot"
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

_ROBOT_MODELS: dict[str, type[_Decision]] = {
    "gripper.move_world": MoveWorld,
    "gripper.rotate_local": RotateLocal,
    "gripper.open": Aperture,
    "gripper.close": Aperture,
    "dual_gripper.move_world": DualMove,
    **{
        f"{side}_gripper.{verb}": Aperture
        for side in ("left", "right", "dual")
        for verb in ("open", "close")
    },
}


def _dual_only(name: str) -> bool:
    return name.startswith(("dual_", "left_", "right_"))


def robot_action_names(arms: Sequence[str]) -> tuple[str, ...]:
    """The robot action names valid in a scene whose controllable arms are `arms`."""
    return tuple(n for n in _ROBOT_MODELS if len(arms) > 1 or not _dual_only(n))


def _field_range(model: type[BaseModel], name: str) -> tuple[float, float]:
    """The (ge, le) bounds of a numeric field, so messages and templates cannot drift."""
    meta = model.model_fields[name].metadata
    return next(m.ge for m in meta if hasattr(m, "ge")), next(
        m.le for m in meta if hasattr(m, "le")
    )


_BOUNDS = {
    "distance_mm": _field_range(MoveWorld, "distance_mm"),
    "angle_deg": _field_range(RotateLocal, "angle_deg"),
}


def _error_message(e: ErrorDetails) -> str:
    """Repair text for one pydantic error: what is valid, and what the model sent."""
    kind, ctx = e["type"], e.get("ctx", {})
    got = e.get("input")
    name = str(e["loc"][-1]) if e["loc"] else ""
    if kind == "missing":
        return "required"
    if kind in ("greater_than_equal", "less_than_equal", "greater_than", "less_than"):
        if name in _BOUNDS:
            low, high = _BOUNDS[name]
            return f"must be between {low:g} and {high:g}, got {_show(got)}"
        bound = next(iter(ctx.items()), ("", ""))
        op = {"ge": ">=", "le": "<=", "gt": ">", "lt": "<"}.get(bound[0], bound[0])
        return f"must be {op} {bound[1]}, got {_show(got)}"
    if kind == "literal_error":
        if name == "sign":
            return (
                "must be '+' or '-' (also accepted: pos, positive, +1, 1, neg, negative, -1), "
                f"got {_show(got)}"
            )
        return f"must be {ctx.get('expected')}, got {_show(got)}"
    if kind in ("float_type", "float_parsing", "finite_number"):
        return f"must be a number, got {_show(got)}"
    if kind in ("int_type", "int_parsing", "int_from_float"):
        return f"must be an integer, got {_show(got)}"
    if kind == "string_too_short":
        return "must not be empty"
    if kind == "string_type":
        return f"must be a string, got {_show(got)}"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return f"must be a JSON object, got {_show(got)}"
    if kind == "list_type":
        return f"must be a list, got {_show(got)}"
    if kind == "too_long":
        return f"must hold at most {ctx.get('max_length')} items, got {ctx.get('actual_length')}"
    if kind == "too_short":
        return f"must hold at least {ctx.get('min_length')} item(s), got {ctx.get('actual_length')}"
    if kind == "value_error":
        return str(ctx.get("error", e["msg"]))
    return e["msg"]


def _location(loc: Sequence[int | str], prefix: str = "") -> str:
    out = prefix
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "action"


def _validation_error(err: ValidationError, prefix: str = "") -> DecisionError:
    problems = [(_location(e["loc"], prefix), _error_message(e)) for e in err.errors()]
    return DecisionError(*problems[0], others=problems[1:])


def _unknown_action(name: Any, valid: Sequence[str]) -> DecisionError:
    if not isinstance(name, str):
        return DecisionError("action", f"must be a string naming the action, got {_show(name)}")
    hint = ""
    if name in TOOL_NAMES:
        hint = f'; \'{name}\' is a tool: {{"tool": "{name}", "args": {{...}}}}'
    elif name == "stop":
        hint = '; to stop, reply {"stop": true}'
    return DecisionError(
        "action", f"unknown action {_show(name)}{hint}; valid actions: {', '.join(valid)}"
    )


def parse_robot_action(
    obj: Any, arms: Sequence[str]
) -> MoveWorld | RotateLocal | Aperture | DualMove:
    """Validate one robot action (a dict as decoded from the model's JSON) for a scene whose
    controllable arms are `arms` (("right",) for single-arm tasks, ("left", "right") for dual).

    Dual-arm tasks require "arm" on `gripper.*` actions; single-arm tasks reject the
    `left_`/`right_`/`dual_` actions. Raises `ActionError` (= `DecisionError`)."""
    if not isinstance(obj, dict):
        raise DecisionError("action", f"expected a JSON object, got {type(obj).__name__}")
    name = obj.get("action")
    if name not in _ROBOT_MODELS:
        raise _unknown_action(name, robot_action_names(arms))
    dual = len(arms) > 1
    if _dual_only(name) and not dual:
        raise DecisionError(
            "action", f"'{name}' needs a dual-arm task; this task uses {list(arms)}"
        )
    try:
        action = _ROBOT_MODELS[name].model_validate(obj)
    except ValidationError as err:
        raise _validation_error(err) from None
    assert isinstance(action, MoveWorld | RotateLocal | Aperture | DualMove)
    if isinstance(action, DualMove) or _dual_only(name):
        if isinstance(action, Aperture) and action.arm is not None:
            raise DecisionError("arm", f"'{name}' already names its gripper; omit 'arm'")
        return action
    if dual and action.arm is None:
        raise DecisionError("arm", "required in dual-arm tasks: 'left' or 'right'")
    if action.arm is not None and action.arm not in arms:
        raise DecisionError("arm", f"'{action.arm}' is not an arm of this task; arms: {list(arms)}")
    return action


# -- camera actions ----------------------------------------------------------------------------

# The names come from the camera model, which implements them (one list, no copies).
CAMERA_VIEWS = _camera.VIEWS
"""The five semantic views, in the fixed order of the passive bundle."""
CAMERA_TARGETS = _camera.TARGETS
"""Explicit view targets of dual-arm tasks (`camera.view_<target>_<view>`)."""
CAMERA_INCREMENTS = _camera.INCREMENTS


def camera_action_names(arms: Sequence[str]) -> tuple[str, ...]:
    """Every camera action name valid in a scene with `arms` (active protocol only)."""
    views = [f"camera.view_{v}" for v in CAMERA_VIEWS]
    if len(arms) > 1:
        views += [f"camera.view_{t}_{v}" for t in CAMERA_TARGETS for v in CAMERA_VIEWS]
    return (*views, *(f"camera.{i}" for i in CAMERA_INCREMENTS))


_ALL_CAMERA_NAMES = camera_action_names(("left", "right"))


class CameraAction(_Decision):
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


def _parse_camera_action(obj: dict[str, Any], ctx: DecisionContext) -> CameraAction:
    name = obj["action"]
    if ctx.protocol == "passive":
        raise DecisionError(
            "action",
            "camera actions are not available in the passive protocol; "
            "the five views are supplied every observation",
        )
    valid = camera_action_names(ctx.arms)
    if name not in valid:
        if name in _ALL_CAMERA_NAMES:
            raise DecisionError(
                "action", f"'{name}' needs a dual-arm task; this task uses {list(ctx.arms)}"
            )
        raise _unknown_action(name, action_names(ctx.arms, ctx.protocol))
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
        raise _validation_error(err) from None


def action_names(arms: Sequence[str], protocol: ObservationProtocol) -> tuple[str, ...]:
    """Robot and (active protocol only) camera action names valid in an episode."""
    cameras = camera_action_names(arms) if protocol == "active" else ()
    return (*robot_action_names(arms), *cameras)


# -- tools -------------------------------------------------------------------------------------

BASE_TOOLS = ("geometry.verify", "camera.history")
DEMONSTRATION_TOOLS = ("expert.retrieve", "expert.frame", "expert.learn")
TOOL_NAMES = (*BASE_TOOLS, *DEMONSTRATION_TOOLS)
ToolName = Literal[
    "geometry.verify", "camera.history", "expert.retrieve", "expert.frame", "expert.learn"
]


def available_tools(demonstration: bool) -> tuple[str, ...]:
    """The tools of an episode: the demonstration tools only when a demonstration exists."""
    return TOOL_NAMES if demonstration else BASE_TOOLS


class _Args(BaseModel):
    model_config = ConfigDict(extra="ignore", frozen=True)


class NoArgs(_Args):
    """`geometry.verify` and `expert.retrieve` take no arguments."""


class HistoryArgs(_Args):
    """`camera.history`: re-attach the model image of an earlier step."""

    step: FrameIndex


class FrameArgs(_Args):
    """`expert.frame`: one frame ("step") or up to 8 ("steps"); "view" is optional."""

    step: FrameIndex | None = None
    steps: Annotated[list[FrameIndex], Field(min_length=1, max_length=MAX_EXPERT_FRAMES)] | None = (
        None
    )
    view: Annotated[str, Field(min_length=1)] | None = None

    @property
    def frames(self) -> tuple[int, ...]:
        """The requested frame indices, in the order asked."""
        return (self.step,) if self.step is not None else tuple(self.steps or ())


def _summary(value: Any) -> Any:
    if isinstance(value, str) and value.strip():
        return value
    if isinstance(value, dict) and value:
        return value
    raise ValueError(f"must be a non-empty string or JSON object, got {_show(value)}")


class LearnArgs(_Args):
    """`expert.learn`: the task summary; its fields are checked by the demonstration tools."""

    summary: Annotated[str | dict[str, Any], BeforeValidator(_summary)]


_TOOL_ARGS: dict[str, type[_Args]] = {
    "geometry.verify": NoArgs,
    "camera.history": HistoryArgs,
    "expert.retrieve": NoArgs,
    "expert.frame": FrameArgs,
    "expert.learn": LearnArgs,
}
_TOOL_FORMS = {
    "geometry.verify": '{"tool": "geometry.verify", "args": {}}',
    "camera.history": '{"tool": "camera.history", "args": {"step": k}} (k >= 0)',
    "expert.retrieve": '{"tool": "expert.retrieve", "args": {}}',
    "expert.frame": (
        '{"tool": "expert.frame", "args": {"step": k} or {"steps": [k, ...]} '
        f'(at most {MAX_EXPERT_FRAMES}), optional "view"}}'
    ),
    "expert.learn": '{"tool": "expert.learn", "args": {"summary": ...}}',
}


class ToolCall(_Decision):
    """A tool call; it never advances the simulator."""

    kind: ClassVar[DecisionKind] = "tool"
    name: ToolName
    args: NoArgs | HistoryArgs | FrameArgs | LearnArgs

    def label(self) -> str:
        if isinstance(self.args, HistoryArgs):
            return f"tool {self.name} step={self.args.step}"
        if isinstance(self.args, FrameArgs):
            frames = ",".join(str(i) for i in self.args.frames)
            view = f" view={self.args.view}" if self.args.view else ""
            return f"tool {self.name} steps={frames}{view}"
        return f"tool {self.name}"


def _parse_tool_call(obj: dict[str, Any], ctx: DecisionContext) -> ToolCall:
    name, args = obj["tool"], obj.get("args", {})
    if not isinstance(name, str):
        raise DecisionError("tool", f"must be a string naming the tool, got {_show(name)}")
    if name not in ctx.tools:
        valid = ", ".join(ctx.tools)
        if name in TOOL_NAMES:
            raise DecisionError(
                "tool", f"'{name}' is not available in this episode; available tools: {valid}"
            )
        hint = ""
        if name in _ROBOT_MODELS or name in _ALL_CAMERA_NAMES:
            hint = f'; \'{name}\' is an action: {{"action": "{name}", ...}}'
        raise DecisionError("tool", f"unknown tool {_show(name)}{hint}; available tools: {valid}")
    if not isinstance(args, dict):
        raise DecisionError("args", f"must be a JSON object, got {_show(args)}")
    try:
        parsed = _TOOL_ARGS[name].model_validate(args)
    except ValidationError as err:
        raise _validation_error(err, prefix="args") from None
    if isinstance(parsed, FrameArgs):
        if parsed.step is not None and parsed.steps is not None:
            raise DecisionError("args", "give either 'step' or 'steps', not both")
        if parsed.step is None and parsed.steps is None:
            raise DecisionError(
                "args.steps",
                f'required: {{"step": k}} or {{"steps": [k, ...]}} (at most {MAX_EXPERT_FRAMES})',
            )
    try:
        return ToolCall(name=name, args=parsed, reason=obj.get("reason"))  # type: ignore[arg-type]
    except ValidationError as err:
        raise _validation_error(err) from None


# -- stop ---------------------------------------------------------------------------------------


class Stop(_Decision):
    """The model ends the episode."""

    kind: ClassVar[DecisionKind] = "stop"
    stop: Literal[True] = True

    def label(self) -> str:
        return "stop"


Decision = MoveWorld | RotateLocal | Aperture | DualMove | CameraAction | ToolCall | Stop


# -- context, extraction, dispatch ------------------------------------------------------------


@dataclass(frozen=True)
class DecisionContext:
    """What one episode allows at the current decision.

    `arms`: ("right",) for single-arm tasks, ("left", "right") for dual-arm (`Task.arms`).
    `protocol`: "active" (camera actions allowed) or "passive" (five fixed views, none).
    `tools`: the tool names offered, `available_tools(demonstration)`.
    `camera_chain`: camera actions executed since the last robot action,
    `camera_chain_length(kinds)`; a camera action is rejected once it reaches
    `MAX_CAMERA_CHAIN`. Per decision: `dataclasses.replace(ctx, camera_chain=...)`.
    """

    arms: tuple[str, ...]
    protocol: ObservationProtocol = "active"
    tools: tuple[str, ...] = BASE_TOOLS
    camera_chain: int = 0

    def __post_init__(self) -> None:
        if (
            not self.arms
            or len(set(self.arms)) != len(self.arms)
            or not set(self.arms)
            <= {
                "left",
                "right",
            }
        ):
            raise ValueError(f"arms must be ('right',) or ('left', 'right'), got {self.arms!r}")
        if self.protocol not in ("active", "passive"):
            raise ValueError(f"protocol must be 'active' or 'passive', got {self.protocol!r}")
        unknown = [t for t in self.tools if t not in TOOL_NAMES]
        if unknown:
            raise ValueError(f"tools: unknown {unknown}; valid tools: {list(TOOL_NAMES)}")
        if self.camera_chain < 0:
            raise ValueError(f"camera_chain must be >= 0, got {self.camera_chain}")


_FENCE = re.compile(r"```([^\n`]*)(.*?)```", re.S)
_DECISION_KEYS = ("action", "tool", "stop")


def _fenced_blocks(text: str) -> list[tuple[str, str]]:
    """(language tag, body) of every ``` fence; `json{...}` on the fence line is body."""
    blocks = []
    for m in _FENCE.finditer(text):
        header = re.match(r"\s*([A-Za-z][\w+.-]*)?(.*)", m[1], re.S)
        assert header is not None  # the pattern matches every string
        blocks.append(((header[1] or "").lower(), (header[2] or "") + m[2]))
    return blocks


def _balanced_spans(text: str) -> tuple[list[tuple[int, int]], bool]:
    """Top-level {...} spans of free text, with braces inside JSON strings ignored.

    A "{" that is never closed (prose, or a reply cut off) is skipped and the scan resumes
    after it, so it cannot swallow the real object; the flag says one was seen.
    """
    spans: list[tuple[int, int]] = []
    unclosed = False
    pos = 0
    while (start := text.find("{", pos)) >= 0:
        depth, in_string, escaped, end = 0, False, False, -1
        for i in range(start, len(text)):
            ch = text[i]
            if in_string:
                if escaped:
                    escaped = False
                elif ch == "\\":
                    escaped = True
                elif ch == '"':
                    in_string = False
            elif ch == '"':
                in_string = True
            elif ch == "{":
                depth += 1
            elif ch == "}":
                depth -= 1
                if depth == 0:
                    end = i + 1
                    break
        if end < 0:
            unclosed = True
            pos = start + 1
        else:
            spans.append((start, end))
            pos = end
    return spans, unclosed


def _decode(body: str, where: str) -> Any:
    try:
        return json.loads(body)
    except json.JSONDecodeError as err:
        raise DecisionError(
            REPLY, f"{where} is not valid JSON: {err.msg} at line {err.lineno} column {err.colno}"
        ) from None


def _as_object(value: Any, where: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        kind = {list: "a list", str: "a string", bool: "a boolean", type(None): "null"}.get(
            type(value), "a number"
        )
        raise DecisionError(REPLY, f"{where} must be one JSON object, got {kind}")
    return value


def extract_json_object(text: str) -> dict[str, Any]:
    """The decision object of a reply (module docstring, "Reply extraction")."""
    if not text.strip():
        raise DecisionError(REPLY, "the reply is empty; reply with one JSON object")
    blocks = _fenced_blocks(text)
    tagged = [body for tag, body in blocks if tag.startswith("json")]
    untagged = [body for tag, body in blocks if not tag and body.lstrip().startswith("{")]
    if tagged or untagged:
        body = (tagged or untagged)[-1]
        return _as_object(_decode(body.strip(), "the ```json block"), "the ```json block")
    try:
        whole = json.loads(text)
    except json.JSONDecodeError:
        pass
    else:
        return _as_object(whole, "the reply")
    spans, unclosed = _balanced_spans(text)
    objects = []
    for start, end in spans:
        try:
            value = json.loads(text[start:end])
        except json.JSONDecodeError:
            continue
        if isinstance(value, dict):
            objects.append(value)
    decisions = [o for o in objects if any(k in o for k in _DECISION_KEYS)]
    if decisions or objects:
        return (decisions or objects)[-1]
    if spans:  # none decodes: report on the last one that looks like a decision
        bodies = [text[start:end] for start, end in spans]
        meant = [b for b in bodies if any(f'"{k}"' in b for k in _DECISION_KEYS)]
        _decode((meant or bodies)[-1], "the JSON object in the reply")
    if unclosed:
        raise DecisionError(
            REPLY,
            "the reply has a '{' without a matching '}' (cut off?); reply with one JSON object",
        )
    raise DecisionError(REPLY, "no JSON object found in the reply")


def decision_from_object(obj: Any, ctx: DecisionContext) -> Decision:
    """Dispatch and validate one decoded decision: "stop": true, then "tool", then "action".

    Does not apply the camera-chain rule (`parse_decision` does)."""
    obj = _as_object(obj, "the decision")
    if "stop" in obj:
        if not isinstance(obj["stop"], bool):
            raise DecisionError("stop", f"must be true or false, got {_show(obj['stop'])}")
        if obj["stop"]:
            try:
                return Stop.model_validate(obj)
            except ValidationError as err:
                raise _validation_error(err) from None
    if "tool" in obj:
        return _parse_tool_call(obj, ctx)
    if "action" not in obj:
        raise DecisionError(
            "action",
            'required: reply with {"action": ...}, {"tool": ..., "args": {...}} or {"stop": true}',
        )
    name = obj["action"]
    if name in _ROBOT_MODELS:
        return parse_robot_action(obj, ctx.arms)
    if isinstance(name, str) and name.startswith("camera."):
        return _parse_camera_action(obj, ctx)
    raise _unknown_action(name, action_names(ctx.arms, ctx.protocol))


def parse_decision(text: str, ctx: DecisionContext) -> Decision:
    """The validated decision of one model reply, or `DecisionError` with repair text.

    Extraction (`extract_json_object`), dispatch and validation (`decision_from_object`),
    then the camera-chain rule (`check_camera_chain` with `ctx.camera_chain`)."""
    decision = decision_from_object(extract_json_object(text), ctx)
    check_camera_chain(decision, ctx.camera_chain)
    return decision


# -- camera chain, labels, vocabulary ---------------------------------------------------------


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


def check_camera_chain(decision: Decision, chain: int) -> None:
    """Reject a camera action that would make the chain longer than `MAX_CAMERA_CHAIN`."""
    if isinstance(decision, CameraAction) and chain >= MAX_CAMERA_CHAIN:
        raise DecisionError(
            "action",
            f"at most {MAX_CAMERA_CHAIN} camera actions in a row; {chain} camera actions since the "
            "last robot action, so the next decision must be a robot action, a tool call or stop",
        )


def decision_label(decision: Decision) -> str:
    """A compact, stable label for records and the action history, e.g.
    "move_world right z+30mm", "camera.view_topdown", "tool geometry.verify", "stop"."""
    return decision.label()


def _robot_forms(arms: Sequence[str]) -> list[str]:
    arm = ', "arm": "left|right"' if len(arms) > 1 else ""
    (d_lo, d_hi), (a_lo, a_hi) = _BOUNDS["distance_mm"], _BOUNDS["angle_deg"]
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
            if _dual_only(n) and _ROBOT_MODELS[n] is Aperture
        ]
        forms.append(
            f'{{"action": "dual_gripper.move_world", "left": {{{move}}}, "right": {{{move}}}}}'
        )
    return forms


def available_actions(
    arms: Sequence[str], protocol: ObservationProtocol, tools: Sequence[str]
) -> list[str]:
    """The decision vocabulary listed in each observation, one template per line: robot
    actions with their ranges (and "arm" in dual-arm tasks), camera actions in the active
    protocol only (dual-arm view targets only in dual-arm tasks), the offered tools, stop."""
    cameras = camera_action_names(arms) if protocol == "active" else ()
    return [
        *_robot_forms(arms),
        *(f'{{"action": "{n}"}}' for n in cameras),
        *(_TOOL_FORMS[t] for t in tools),
        '{"stop": true}',
    ]
