"""The model-facing decision layer (spec FACTS.md, "Model-facing protocol").

One model reply carries one decision, a JSON object: a robot action (executed by the
simulator), a camera action (moves the observation camera only), a tool call (never advances
the simulator) or a stop. This package turns the reply text into a validated, immutable
decision, or raises `DecisionError(field, message)` whose text is written to be sent back to
the model as repair feedback. One concept a module:

- `vocabulary`: the names, ranges and budgets (no parsing);
- `errors`: `DecisionError` and the repair text of pydantic's errors;
- `robot`: robot actions, `parse_robot_action(obj, arms)` (what the simulator uses alone);
- `camera`: camera actions and the camera-chain rule;
- `tools`: tool calls and their arguments;
- `extract`: reasoning kept apart, and the decision object found in free text, as the
  benchmark's reference harness finds it;
- `aliases`: the reference's spellings of a decision rewritten into one form;
- `context`: `DecisionContext`, what one episode allows;
- `decision`: dispatch, `parse_decision`, labels and the vocabulary listed to the model.

What the episode engine calls:

- `DecisionContext(arms, protocol, tools, camera_chain)`: what this episode allows.
  `available_tools(demonstration)` gives `tools`; `camera_chain_length(kinds)` gives
  `camera_chain` from the kinds of the decisions executed so far.
- `parse_decision(text, ctx) -> Decision`: extraction, aliases, dispatch, validation.
  `split_reasoning(text)` gives a reply's (answer, inline reasoning).
  `decision_from_object(obj, ctx)` does the same for an already decoded JSON object.
- `decision_label(decision)`: the compact label recorded in events and shown in the history.
- `available_actions(arms, protocol, tools)`: the vocabulary listed in every observation.
- `MAX_REPAIRS_PER_DECISION`, `MAX_TOOL_ROUND_TRIPS`, `MAX_CAMERA_CHAIN`: the budgets.

Decisions the spec leaves open are documented where they are made: reply extraction and
inline reasoning in `extract`, the accepted spellings in `aliases`, dispatch and unknown keys
in `decision`, the camera chain in `camera`, the
`expert.learn` summary in `tools`.
"""

from vabench.protocol.aliases import SIGN_ALIASES, normalise
from vabench.protocol.camera import (
    CameraAction,
    action_names,
    camera_chain_length,
)
from vabench.protocol.context import DecisionContext
from vabench.protocol.decision import (
    Decision,
    Stop,
    available_actions,
    decision_from_object,
    decision_label,
    parse_decision,
)
from vabench.protocol.errors import REPLY, ActionError, DecisionError
from vabench.protocol.extract import extract_json_object, split_reasoning
from vabench.protocol.robot import (
    AnyRobotAction,
    Aperture,
    Arm,
    AxisMove,
    DualMove,
    GripperName,
    MoveWorld,
    RobotAction,
    RotateLocal,
    RotateWorld,
    parse_robot_action,
    robot_action_names,
)
from vabench.protocol.tools import (
    FrameArgs,
    HistoryArgs,
    LearnArgs,
    NoArgs,
    ToolCall,
)
from vabench.protocol.vocabulary import (
    BASE_TOOLS,
    CAMERA_INCREMENTS,
    CAMERA_TARGETS,
    CAMERA_VIEWS,
    DEMONSTRATION_TOOLS,
    LEARNING_STAGE_MARK,
    MAX_CAMERA_CHAIN,
    MAX_EXPERT_FRAMES,
    MAX_REPAIRS_PER_DECISION,
    MAX_TOOL_ROUND_TRIPS,
    TOOL_NAMES,
    DecisionKind,
    ObservationProtocol,
    ToolName,
    available_tools,
    camera_action_names,
)

__all__ = [
    "BASE_TOOLS",
    "CAMERA_INCREMENTS",
    "CAMERA_TARGETS",
    "CAMERA_VIEWS",
    "DEMONSTRATION_TOOLS",
    "LEARNING_STAGE_MARK",
    "MAX_CAMERA_CHAIN",
    "MAX_EXPERT_FRAMES",
    "MAX_REPAIRS_PER_DECISION",
    "MAX_TOOL_ROUND_TRIPS",
    "REPLY",
    "SIGN_ALIASES",
    "TOOL_NAMES",
    "ActionError",
    "AnyRobotAction",
    "Aperture",
    "Arm",
    "AxisMove",
    "CameraAction",
    "Decision",
    "DecisionContext",
    "DecisionError",
    "DecisionKind",
    "DualMove",
    "FrameArgs",
    "GripperName",
    "HistoryArgs",
    "LearnArgs",
    "MoveWorld",
    "NoArgs",
    "ObservationProtocol",
    "RobotAction",
    "RotateLocal",
    "RotateWorld",
    "Stop",
    "ToolCall",
    "ToolName",
    "action_names",
    "available_actions",
    "available_tools",
    "camera_action_names",
    "camera_chain_length",
    "decision_from_object",
    "decision_label",
    "extract_json_object",
    "normalise",
    "parse_decision",
    "parse_robot_action",
    "robot_action_names",
    "split_reasoning",
]
