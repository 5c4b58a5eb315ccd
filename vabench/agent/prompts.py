"""The system prompt of an episode: the role, the generic manipulation and safety rules, the
task profiles and the held-out policy, the reply protocol and the action interface (paper,
appendices "Agent harness" and "Demonstration and prompt conditioning"; the reference's facts
in spec PROTOCOL_FACTS.md, sections 1.1-1.7; docs/PROTOCOL.md lists each point).

`system_prompt(arms, protocol, tools, task=...)` assembles it from sections, so that what
differs between conditions is visible here and nowhere else:

- dual-arm rules only when `arms` has two arms;
- the camera section only in the active protocol; the passive protocol gets the five-view
  section instead and no camera word in its action vocabulary;
- a task profile only for the tasks that need roles or a completion rule spelled out
  (`TASK_PROFILES`: lift_pot, handover_horizontal_block, put_everything_in_basket), and the
  held-out policy only for the `<base>_heldout` tasks;
- one line per offered tool.

The instruction, the demonstration summary and the available actions arrive with each
observation. The prompt gives no number about the scene or the cameras (no object position,
no camera position or lens) and states no step budget: only the robot's own frame, ranges and
step sizes. `visibility.EVALUATOR_ONLY_TERMS` are avoided (tests check it).
"""

from __future__ import annotations

import typing
from collections.abc import Sequence

from vabench.agent.observation import INITIAL_VIEW, PASSIVE_VIEWS
from vabench.agent.prompt_rules import GENERIC_RULES, HELDOUT_RULES, RULE_HANDLING, TASK_PROFILES
from vabench.protocol import MAX_TOOL_ROUND_TRIPS, ObservationProtocol

PROTOCOLS: tuple[str, ...] = typing.get_args(ObservationProtocol)
HELDOUT_SUFFIX = "_heldout"

TOOL_DOCS: dict[str, str] = {
    "geometry.verify": (
        '{"tool": "geometry.verify", "args": {}}: the robot\'s own geometry (gripper aperture, '
        "finger dimensions, where GC and the control point lie, axis definitions, reach bounds, "
        "arm base positions)."
    ),
    "camera.history": (
        '{"tool": "camera.history", "args": {"step": k}}: shows again the image you received at '
        "observation step k."
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


def _rule_block(title: str, rules: Sequence[tuple[str, str]]) -> str:
    lines = "\n".join(f"- [{rule_id}] {text}" for rule_id, text in rules)
    return f"# {title}\n{RULE_HANDLING}\n{lines}"


def _intro(dual: bool, protocol: str) -> str:
    robot = "two robot arms (left and right)" if dual else "one robot arm"
    images = (
        "one image from the current camera view"
        if protocol == "active"
        else "five images from fixed views around the gripper" + ("s" if dual else "")
    )
    return (
        f"You are an active-spatial manipulation agent: you control {robot} with "
        "parallel-jaw grippers at a table, in simulation. Each of your replies is one "
        "decision: a robot action, "
        + ("a camera action, " if protocol == "active" else "")
        + "a tool call, or stop. After every robot"
        + (" or camera" if protocol == "active" else "")
        + " action you receive a new observation: the observation step, the task "
        "instruction, the gripper state, the robot self-geometry, the actions executed so "
        f"far, the decisions available now, and {images}. The episode ends by itself as "
        "soon as the task is accomplished (you are not told), or when you stop."
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
- Positions are in metres in the world frame, angles in degrees; quaternions are (w, x, y, z);
  control_eepose_rpy_deg is roll, pitch, yaw with R = Rz(yaw) Ry(pitch) Rx(roll).
- finger_center_xyz is GC, the midpoint between the two finger pads. The fingertips reach 15 mm
  beyond GC along rx. control_eepose_xyz is the controlled point on the palm face, behind GC.
- local_axes_world gives the gripper's axes as unit vectors in the world frame: rx = approach
  axis (from the palm towards the fingertips), ry = finger-closing axis (the direction in which
  the fingers move), rz = palm-side axis (perpendicular to both).
- The robot self-geometry adds, per arm, the direction from the control point to GC, its
  length, its angles to the six world axis directions and to the table's downward normal, and
  whether that angle is within 30 and 45 deg (a top-down posture).
- The fingers open to at most 90 mm apart. is_open and is_closed follow the last open/close
  command.
- last_action_valid is false when the previous action was rejected by the robot;
  last_planner_success is false when the planner could not carry it out (the arm then stays
  where it stopped). Both are true at the start and after camera actions.
- Targets of the control point are kept inside x [-0.55, 0.55], y [-0.45, 0.35],
  z [0.74, 1.35] m."""


def _robot_actions(dual: bool, protocol: str) -> str:
    arm = ', "arm": "left"|"right"' if dual else ""
    if protocol == "active":
        look = (
            "- Look before moving in x/y: do not make a world x or y move the first action "
            f'from an oblique view or the head camera ("{INITIAL_VIEW}"); take '
            "camera.view_topdown first. Every x/y move's reason names the direction evidence "
            "(e.g. the object lies +y of GC); when the direction is uncertain or only "
            "perspective suggests it, look from above. A large x/y move needs fresh topdown "
            "evidence after the gripper's last change of pose."
        )
    else:
        look = (
            "- Take world x/y directions from the topdown image, and name the direction "
            "evidence in every x/y move's reason (e.g. the object lies +y of GC)."
        )
    text = f"""# Robot actions
- {{"action": "gripper.move_world", "axis": "x"|"y"|"z", "sign": "+"|"-", "distance_mm": N{arm}}}
  N from 1 to 100: moves the gripper by N millimetres along a fixed world axis in one straight
  line, whatever the camera shows; the orientation is kept. A target outside the bounds is
  clipped to them.
- {{"action": "gripper.rotate_local", "axis": "rx"|"ry"|"rz", "sign": "+"|"-", "angle_deg": A{arm}}}
  A from 1 to 90: rotates the gripper about its own current axis; + is a right-hand rotation
  (counter-clockwise when the axis points at you). GC is held in place through waypoints of at
  most 10 deg, so the control point moves. A rotation any of whose waypoints would take the
  control point outside the bounds is refused as a whole (nothing moves, the planner reports
  failure); the planner may also stop one midway, leaving the turn partial. Rotations avoid no
  collisions: make room first (look, move up in z, or move a little sideways).
- {{"action": "gripper.open"{arm}}}, {{"action": "gripper.close"{arm}}}: change the aperture only.
- Signs may also be written "pos"/"neg", "positive"/"negative", 1/-1.
{look}
- The planner avoids only the table, not objects: a gripper moved into an object pushes it."""
    if dual:
        text += """

# Two arms
- gripper.move_world, gripper.rotate_local, gripper.open and gripper.close require
  "arm": "left" or "right"; without it they are invalid. There is no hidden selected arm.
- {"action": "left_gripper.open"}, {"action": "left_gripper.close"},
  {"action": "right_gripper.open"}, {"action": "right_gripper.close"}: one named gripper.
- {"action": "dual_gripper.open"}, {"action": "dual_gripper.close"}: both grippers in the same
  step.
- {"action": "dual_gripper.move_world", "left": {"axis": ..., "sign": ..., "distance_mm": N},
  "right": {"axis": ..., "sign": ..., "distance_mm": N}}: both arms move in the same step, in
  one planned motion; invalid if either side is invalid. Use it whenever success needs the
  arms to move together (a two-handed lift).
- left and right name the robot's arms, not sides of an image; camera motion never changes
  what an arm's world-axis command means.
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
objects stay where they are, and the camera does not follow the gripper afterwards. Each
camera action costs one step, like a robot action. The observation does not name the current
view: it is the one your last camera actions chose. Camera actions take no parameters, e.g.
{{"action": "camera.view_side"}}.
Views centred on the gripper (the camera moves to a fixed offset from GC and looks at GC, at
the moment the view is taken):
{views}{targets}
Adjustments of the current view:
- camera.move_left, camera.move_right, camera.move_up, camera.move_down: 5 cm along the
  camera's left, right, up or down direction.
- camera.zoom_in, camera.zoom_out: 8 cm forward or backward along the viewing direction.
- camera.yaw_left, camera.yaw_right: the camera turns in place 10 deg about the vertical
  (world z) axis; yaw_left turns the view to the left.
- camera.pitch_up, camera.pitch_down: the camera turns in place 10 deg about its own left axis,
  pitch_up by a right-hand (positive) turn, which tilts the view downwards; pitch_down tilts it
  upwards.
Turns keep the camera's position; what it looks at moves. The camera stays inside a bounded
region; a view never changes the world-frame meaning of robot actions."""


def _passive(dual: bool) -> str:
    listing = "\n".join(f"{i}. {v}: {_VIEW_DOCS[v]}." for i, v in enumerate(PASSIVE_VIEWS, 1))
    centre = "the midpoint between the two GCs" if dual else "the gripper (GC)"
    return f"""# Views
Every observation brings five fixed views, always in this order, and they are your only
visual input:
{listing}
All five are centred on {centre}. The images carry no labels: their order tells which
view is which. Issue no camera.* action: there are none in this condition."""


def _tools(tools: Sequence[str]) -> str:
    if not tools:
        return ""
    lines = "\n".join(f"- {TOOL_DOCS[t]}" for t in tools)
    return f"""# Tools
Tools never move the robot and cost no step; their result comes back as the next message.
At most {MAX_TOOL_ROUND_TRIPS} model replies per step, tool calls and corrected replies
included.
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
Reply with exactly one JSON command, alone or in one ```json fenced block after your
thinking. Every decision may carry an optional "reason" string. A decision is an "action", a
"tool" with its "args" object, or {{"stop": true}}, which ends the episode. Examples:
{shown}
A malformed or invalid reply comes back with the error; correct it in the next reply (a
rejected reply costs no step, but a decision ends the episode after repeated failures)."""


def system_prompt(
    arms: Sequence[str], protocol: str, tools: Sequence[str], *, task: str | None = None
) -> str:
    """The system prompt for a task with `arms` (("right",) or ("left", "right")) under
    `protocol` ("active" or "passive") offering `tools` (names of `TOOL_DOCS`, in order);
    `task` (the task's name) selects its profile and, for `<base>_heldout`, the held-out
    policy.

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
    base = task.removesuffix(HELDOUT_SUFFIX) if task else None
    sections = [
        _intro(dual, protocol),
        _rule_block("Manipulation and safety rules", GENERIC_RULES),
        _passive(dual) if protocol == "passive" else "",
        _rule_block("Held-out evaluation", HELDOUT_RULES)
        if task and task.endswith(HELDOUT_SUFFIX)
        else "",
        _rule_block(f"Task profile: {base}", TASK_PROFILES[base]) if base in TASK_PROFILES else "",
        _frame(arms),
        _robot_actions(dual, protocol),
        _camera(dual) if protocol == "active" else "",
        _tools(tools),
        _reply(dual, protocol, tools),
    ]
    return "\n\n".join(s for s in sections if s) + "\n"
