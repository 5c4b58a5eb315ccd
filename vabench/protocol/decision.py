"""One decision from one reply: dispatch, validation, labels, and the
vocabulary listed in every observation.

Dispatch, as the benchmark's reference harness does it (PROTOCOL_FACTS 3.3): first the
spellings the reference accepts are rewritten into one form (`aliases.normalise`: null fields
absent, `tool_name`/`tool_args`, tool names as actions, axis and sign spellings, legacy
compact names); then `"stop": true` wins (the boolean only; any other key is ignored), then
"tool" (a missing "args" means {}), then "action". Unknown keys are ignored, except "arm" on
a camera action, which is rejected with a hint to use `camera.view_left_*` /
`camera.view_right_*` (ignoring it would silently aim elsewhere).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar, Literal

from pydantic import ValidationError

from vabench.protocol.aliases import normalise
from vabench.protocol.camera import (
    CameraAction,
    action_names,
    parse_camera_action,
)
from vabench.protocol.context import DecisionContext
from vabench.protocol.errors import DecisionError, decision_error, unknown_action
from vabench.protocol.extract import as_object, extract_json_object
from vabench.protocol.robot import (
    ROBOT_MODELS,
    Aperture,
    DecisionModel,
    DualMove,
    MoveWorld,
    RotateLocal,
    RotateWorld,
    parse_robot_action,
    robot_forms,
)
from vabench.protocol.tools import TOOL_FORMS, ToolCall, parse_tool_call
from vabench.protocol.vocabulary import DecisionKind, ObservationProtocol, camera_action_names


class Stop(DecisionModel):
    """The model ends the episode."""

    kind: ClassVar[DecisionKind] = "stop"
    stop: Literal[True] = True

    def label(self) -> str:
        return "stop"


Decision = (
    MoveWorld | RotateLocal | RotateWorld | Aperture | DualMove | CameraAction | ToolCall | Stop
)


def decision_from_object(obj: Any, ctx: DecisionContext) -> Decision:
    """Dispatch and validate one decoded decision (module docstring): the reference's
    spellings rewritten, then "stop": true, then "tool", then "action"."""
    obj = normalise(as_object(obj, "the decision"))
    if obj.get("stop") is True:
        try:
            return Stop.model_validate(obj)
        except ValidationError as err:
            raise decision_error(err) from None
    if "tool" in obj:
        return parse_tool_call(obj, ctx)
    if "action" not in obj:
        raise DecisionError(
            "action",
            'required: reply with {"action": ...}, {"tool": ..., "args": {...}} or {"stop": true}',
        )
    name = obj["action"]
    if name in ROBOT_MODELS:
        return parse_robot_action(obj, ctx.arms)
    if isinstance(name, str) and name.startswith("camera."):
        return parse_camera_action(obj, ctx)
    raise unknown_action(name, action_names(ctx.arms, ctx.protocol))


def parse_decision(text: str, ctx: DecisionContext) -> Decision:
    """The validated decision of one model reply, or `DecisionError` with repair text.

    Extraction (`extract_json_object`), dispatch and validation (`decision_from_object`).
    The camera-chain limit is an instruction of the system prompt, not a rejection (paper,
    "the agent instruction limits camera-only chains"; the reference enforces none)."""
    return decision_from_object(extract_json_object(text), ctx)


def decision_label(decision: Decision) -> str:
    """A compact, stable label for records and the action history, e.g.
    "move_world right z+30mm", "camera.view_topdown", "tool geometry.verify", "stop"."""
    return decision.label()


def available_actions(
    arms: Sequence[str], protocol: ObservationProtocol, tools: Sequence[str]
) -> list[str]:
    """The decision vocabulary listed in each observation, one template per line: robot
    actions with their ranges (and "arm" in dual-arm tasks), camera actions in the active
    protocol only (dual-arm view targets only in dual-arm tasks), the offered tools, stop."""
    cameras = camera_action_names(arms) if protocol == "active" else ()
    return [
        *robot_forms(arms),
        *(f'{{"action": "{n}"}}' for n in cameras),
        *(TOOL_FORMS[t] for t in tools),
        '{"stop": true}',
    ]
