"""The system prompt of an episode: the action interface, the camera interface, the reply
protocol and generic manipulation rules (spec FACTS.md "Model-facing protocol"; paper,
appendix "Agent harness").

`system_prompt(arms, protocol, tools)` assembles it from sections, so that what differs
between conditions is visible here and nowhere else:

- dual-arm rules only when `arms` has two arms;
- the camera section only in the active protocol; the passive protocol gets the five-view
  section instead and no camera word in its action vocabulary;
- one line per offered tool.

Nothing task-specific goes in: the instruction, the demonstration summary and the available
actions arrive with each observation. The prompt gives no number about the scene or the
cameras (no object position, no camera position or lens): only the robot's own frame, ranges
and step sizes. `visibility.EVALUATOR_ONLY_TERMS` are avoided (tests check it).
"""

from __future__ import annotations

import typing
from collections.abc import Sequence

from vabench.agent.observation import INITIAL_VIEW, PASSIVE_VIEWS
from vabench.protocol import MAX_CAMERA_CHAIN, MAX_TOOL_ROUND_TRIPS, ObservationProtocol

PROTOCOLS: tuple[str, ...] = typing.get_args(ObservationProtocol)

TOOL_DOCS: dict[str, str] = {
    "geometry.verify": (
        '{"tool": "geometry.verify", "args": {}}: the robot\'s own geometry (gripper aperture, '
        "finger dimensions, where GC and the control point lie, axis definitions, reach bounds, "
        "arm base positions)."
    ),
    "camera.history": (
        '{"tool": "camera.history", "args": {"step": k}}: shows again the image you received at '
        "step k."
    ),
    "expert.retrieve": (
        '{"tool": "expert.retrieve", "args": {}}: lists the frames of the demonstration video '
        "(RGB only, from the head camera)."
    ),
    "expert.frame": (
        '{"tool": "expert.frame", "args": {"step": k} or {"steps": [k1, k2, ...]}}: shows '
        "demonstration frames (at most 8 per call)."
    ),
    "expert.learn": (
        '{"tool": "expert.learn", "args": {"summary": {...}}}: stores your summary of the '
        "demonstration; accepted after you have inspected at least 3 distinct frames."
    ),
}

_VIEW_DOCS = {
    "topdown": "from straight above: left-right and forward-back offsets, in-plane rotation",
    "side": (
        "from the arm's outer side at about gripper height: heights, clearance above the "
        "table, vertical overlap"
    ),
    "front_side_45": (
        "from the robot's side of the table and the arm's outer side, 45 deg around, slightly "
        "above: breaks front and side occlusions"
    ),
    "side_top_45": (
        "from the outer side and above, 45 deg down: lateral alignment, height and finger "
        "placement together"
    ),
    "oblique_45": "from the robot's side, the outer side and above: the overall 3D layout",
}


def _intro(dual: bool, protocol: str) -> str:
    robot = "two robot arms (left and right)" if dual else "one robot arm"
    if protocol == "active":
        images = "one image from the current camera view"
        retention = (
            "The last few images stay in the conversation; older ones are replaced by a note "
            'such as "[image from step 7 omitted]".'
        )
    else:
        images = "five images from fixed views around the gripper" + ("s" if dual else "")
        retention = (
            "Only the current five images are sent; earlier ones are replaced by a note such "
            'as "[five images from step 7 omitted]".'
        )
    return (
        f"You control {robot} with parallel-jaw grippers at a table, in simulation. Each of "
        "your replies is one decision: a robot action, "
        + ("a camera action, " if protocol == "active" else "")
        + "a tool call, or stop. After every robot"
        + (" or camera" if protocol == "active" else "")
        + " action you receive a new observation: the step count and budget, the task "
        "instruction, the current view, the robot state, the previous action's outcome, the "
        "actions executed so far, a demonstration summary when one exists, the decisions "
        f"available now, and {images}. {retention} The episode ends as soon as the task is "
        "accomplished, when you stop, or when the step budget is used up."
    )


def _frame(arms: tuple[str, ...]) -> str:
    dual = len(arms) > 1
    if dual:
        halves = "The right arm works the x > 0 half of the table, the left arm the x < 0 half."
    elif arms == ("right",):
        halves = "The arm works the right (x > 0) half of the table."
    else:
        halves = "The arm works the left (x < 0) half of the table."
    return f"""# Frame, units and robot state
- World frame: x points to the robot's right, y points away from the robot (towards the far
  side of the table), z points up. {halves}
- Robot state positions are in metres in the world frame, angles in degrees; control_eepose_quat
  is (w, x, y, z); control_eepose_rpy_deg is roll, pitch, yaw with R = Rz(yaw) Ry(pitch) Rx(roll).
- finger_center_xyz is GC, the midpoint between the two finger pads. The fingertips reach 15 mm
  beyond GC along rx. control_eepose_xyz is the controlled point on the palm face, behind GC.
- local_axes_world gives the gripper's axes as unit vectors in the world frame: rx = approach
  axis (from the palm towards the fingertips), ry = finger-closing axis (the direction in which
  the fingers move), rz = palm-side axis (perpendicular to both).
- The fingers open to at most 90 mm apart. is_open is the last open/close command.
- last_action_valid is false when the previous action was rejected; last_planner_success is
  false when the planner could not reach the previous target (the arm then stays where it was).
  Both are null before the first action.
- Targets of the control point are kept inside x [-0.55, 0.55], y [-0.45, 0.35],
  z [0.74, 1.35] m."""


def _robot_actions(dual: bool) -> str:
    arm = ', "arm": "left"|"right"' if dual else ""
    text = f"""# Robot actions
- {{"action": "gripper.move_world", "axis": "x"|"y"|"z", "sign": "+"|"-", "distance_mm": N{arm}}}
  N from 1 to 100: moves the gripper by N millimetres along a fixed world axis in one straight
  line; the orientation is kept.
- {{"action": "gripper.rotate_local", "axis": "rx"|"ry"|"rz", "sign": "+"|"-", "angle_deg": A{arm}}}
  A from 1 to 90: rotates the gripper about its own current axis; + is a right-hand rotation
  (counter-clockwise when the axis points at you). GC stays fixed.
- {{"action": "gripper.open"{arm}}}, {{"action": "gripper.close"{arm}}}
- Signs may also be written "pos"/"neg", "positive"/"negative", 1/-1.
- The planner avoids only the table, not objects: a gripper moved into an object pushes it."""
    if dual:
        text += """

# Two arms
- gripper.move_world, gripper.rotate_local, gripper.open and gripper.close require
  "arm": "left" or "right".
- {"action": "left_gripper.open"}, {"action": "left_gripper.close"},
  {"action": "right_gripper.open"}, {"action": "right_gripper.close"}: one named gripper.
- {"action": "dual_gripper.open"}, {"action": "dual_gripper.close"}: both grippers in the same
  step.
- {"action": "dual_gripper.move_world", "left": {"axis": ..., "sign": ..., "distance_mm": N},
  "right": {"axis": ..., "sign": ..., "distance_mm": N}}: both arms move in the same step;
  invalid if either side is invalid.
- The robot state lists both arms; decide which arm does what and keep them from colliding."""
    return text


def _camera(dual: bool) -> str:
    views = "\n".join(f"- camera.view_{v}: {doc}." for v, doc in _VIEW_DOCS.items())
    targets = (
        """
In this two-arm task the views above centre on the midpoint between the two GCs (outer side
= the right side); camera.view_left_<view>, camera.view_right_<view> and
camera.view_both_<view> (for each of the five views) centre on the left GC, the right GC or
the midpoint, with the outer side of that arm."""
        if dual
        else ""
    )
    return f"""# Camera
The first image comes from the head camera (view "{INITIAL_VIEW}"), which looks over the
robot at the workspace. Camera actions move only the observation camera: the robot and the
objects stay where they are. Each camera action costs one step of the budget, like a robot
action. At most {MAX_CAMERA_CHAIN} camera actions may come in a row; after that the next
action must be a robot action. Camera actions take no parameters, e.g.
{{"action": "camera.view_side"}}.
Views centred on the gripper (the camera moves to a fixed offset from GC and looks at GC):
{views}{targets}
Adjustments of the current view:
- camera.move_left, camera.move_right, camera.move_up, camera.move_down: 5 cm along the
  image's left, right, up or down direction.
- camera.zoom_in, camera.zoom_out: 8 cm forward or backward along the viewing direction.
- camera.yaw_left, camera.yaw_right: turn the view 10 deg to the left or right about the
  vertical (world z) axis.
- camera.pitch_up, camera.pitch_down: tilt the view 10 deg up or down about the camera's left
  axis.
Turns keep the point the camera looks at in the middle of the image (the camera orbits it).
After adjustments the view name reads e.g. "topdown (adjusted)".
The camera stays inside a bounded region; a view never changes the world-frame meaning of
robot actions."""


def _passive(dual: bool) -> str:
    listing = "\n".join(f"{i}. {v}: {_VIEW_DOCS[v]}." for i, v in enumerate(PASSIVE_VIEWS, 1))
    centre = "the midpoint between the two GCs" if dual else "the gripper (GC)"
    return f"""# Views
Every observation brings five images, always in this order:
{listing}
All five are centred on {centre}. The images carry no labels: their order tells which
view is which. The views are fixed; there are no camera actions."""


def _tools(tools: Sequence[str]) -> str:
    if not tools:
        return ""
    lines = "\n".join(f"- {TOOL_DOCS[t]}" for t in tools)
    return f"""# Tools
Tools never move the robot and cost no step; their result comes back as the next message.
At most {MAX_TOOL_ROUND_TRIPS} replies per step, tool calls included.
{lines}"""


def _reply(dual: bool, protocol: str, tools: Sequence[str]) -> str:
    arm = ', "arm": "right"' if dual else ""
    examples = [
        f'{{"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 30{arm}, '
        '"reason": "lower towards the table"}',
        f'{{"action": "gripper.rotate_local", "axis": "rx", "sign": "+", "angle_deg": 45{arm}}}',
        f'{{"action": "gripper.close"{arm}}}',
    ]
    if protocol == "active":
        examples.append('{"action": "camera.view_topdown", "reason": "check the alignment"}')
    if "geometry.verify" in tools:
        examples.append('{"tool": "geometry.verify", "args": {}}')
    examples.append('{"stop": true, "reason": "the task is done"}')
    shown = "\n".join(examples)
    return f"""# Reply format
Reply with exactly one JSON object: alone, or in a ```json fenced block after your thinking.
Every decision may carry an optional "reason" string. A decision is an "action", a "tool"
with its "args" object, or {{"stop": true}}, which ends the episode. Examples:
{shown}
A malformed or invalid reply comes back with the error and the current observation; correct
it in the next reply."""


def _rules() -> str:
    return """# How to work
- Object positions are not given: judge them from the images, using the gripper, whose
  position you know exactly, as the reference.
- One action at a time; check the result in the next observation before going on. Use large
  moves away from objects and small ones (5-20 mm) close to them.
- Open the gripper before approaching an object. Before closing, make sure the object lies
  between the fingers, centred along ry and deep enough along rx.
- After closing, lift a little and check in the image that the object came along.
- Keep the fingers clear of the table and of objects you do not mean to touch.
- If the planner fails, try a smaller step, another order of moves or another orientation."""


def system_prompt(arms: Sequence[str], protocol: str, tools: Sequence[str]) -> str:
    """The system prompt for a task with `arms` (("right",) or ("left", "right")) under
    `protocol` ("active" or "passive") offering `tools` (names of `TOOL_DOCS`, in order).

    Raises ValueError naming the bad argument. The passive protocol cannot offer
    camera.history: its requests carry only the current five-image bundle (paper, passive
    protocol).
    """
    arms = tuple(arms)
    if not arms or len(set(arms)) != len(arms) or any(a not in ("left", "right") for a in arms):
        raise ValueError(f"arms: expected ('right',) or ('left', 'right'), got {arms}")
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol: expected one of {PROTOCOLS}, got {protocol!r}")
    unknown = [t for t in tools if t not in TOOL_DOCS]
    if unknown:
        raise ValueError(f"tools: unknown tool {unknown[0]!r}; tools: {list(TOOL_DOCS)}")
    if protocol == "passive" and "camera.history" in tools:
        raise ValueError("tools: camera.history is not offered in the passive protocol")
    dual = len(arms) > 1
    sections = [
        _intro(dual, protocol),
        _frame(arms),
        _robot_actions(dual),
        _camera(dual) if protocol == "active" else _passive(dual),
        _tools(tools),
        _reply(dual, protocol, tools),
        _rules(),
    ]
    return "\n\n".join(s for s in sections if s) + "\n"
