"""Tool calls: `{"tool": name, "args": {...}}`. A tool never advances the simulator.

`geometry.verify` and `camera.history` exist in every episode; the demonstration tools
(`expert.retrieve`, `expert.frame`, `expert.learn`) only where a demonstration exists
(`available_tools`). A missing "args" means {}. `expert.learn` takes the summary fields as its
args object, whatever they are: checking them belongs to the demonstration tools
(`vabench.agent.summary`), so that a wrong field is the tool's error (a model call spent), not a
repair, as in the benchmark's reference harness.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    model_serializer,
    model_validator,
)

from vabench.protocol.context import DecisionContext
from vabench.protocol.errors import DecisionError, decision_error, show
from vabench.protocol.robot import ROBOT_MODELS, DecisionModel, no_bool
from vabench.protocol.vocabulary import (
    ALL_CAMERA_NAMES,
    MAX_EXPERT_FRAMES,
    TOOL_NAMES,
    DecisionKind,
    ToolName,
)

FrameIndex = Annotated[int, BeforeValidator(no_bool), Field(ge=0)]


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


class LearnArgs(_Args):
    """`expert.learn`: the summary fields as the model wrote them (the whole args object);
    the demonstration tools check them. Dumped as that object again."""

    fields: dict[str, Any]

    @model_validator(mode="before")
    @classmethod
    def _whole(cls, data: Any) -> Any:
        return {"fields": data} if isinstance(data, dict) else data

    @model_serializer
    def _dump(self) -> dict[str, Any]:
        return dict(self.fields)


_TOOL_ARGS: dict[str, type[_Args]] = {
    "geometry.verify": NoArgs,
    "camera.history": HistoryArgs,
    "expert.retrieve": NoArgs,
    "expert.frame": FrameArgs,
    "expert.learn": LearnArgs,
}
TOOL_FORMS = {
    "geometry.verify": '{"tool": "geometry.verify", "args": {}}',
    "camera.history": '{"tool": "camera.history", "args": {"step": k}} (k >= 0)',
    "expert.retrieve": '{"tool": "expert.retrieve", "args": {}}',
    "expert.frame": (
        '{"tool": "expert.frame", "args": {"step": k} or {"steps": [k, ...]} '
        f'(at most {MAX_EXPERT_FRAMES}), optional "view"}}'
    ),
    "expert.learn": '{"tool": "expert.learn", "args": {"grasp_object_part": ..., ...}}',
}
"""The template of each tool call, as listed in every observation."""


class ToolCall(DecisionModel):
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


def parse_tool_call(obj: dict[str, Any], ctx: DecisionContext) -> ToolCall:
    """Validate a decision that has a "tool" key, against the tools `ctx` offers."""
    name, args = obj["tool"], obj.get("args", {})
    if not isinstance(name, str):
        raise DecisionError("tool", f"must be a string naming the tool, got {show(name)}")
    if name not in ctx.tools:
        valid = ", ".join(ctx.tools)
        if name in TOOL_NAMES:
            raise DecisionError(
                "tool", f"'{name}' is not available in this episode; available tools: {valid}"
            )
        hint = ""
        if name in ROBOT_MODELS or name in ALL_CAMERA_NAMES:
            hint = f'; \'{name}\' is an action: {{"action": "{name}", ...}}'
        raise DecisionError("tool", f"unknown tool {show(name)}{hint}; available tools: {valid}")
    if not isinstance(args, dict):
        raise DecisionError("args", f"must be a JSON object, got {show(args)}")
    try:
        parsed = _TOOL_ARGS[name].model_validate(args)
    except ValidationError as err:
        raise decision_error(err, prefix="args") from None
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
        raise decision_error(err) from None
