"""Reading a request: the latest observation (text and image) and the agent's own memo.

The agent keeps no state between requests. What it needs to remember (the plan it is
executing, where it saw the objects) it writes into the `reason` of each reply as
`... | memo {json}`; the conversation carries that reply back as the last assistant turn, so
the next request holds it. Only the last assistant turn is read, so history compaction (which
keeps the recent turns) never loses it.

The observation text is the one `vabench.agent.observation.render_observation` writes
("Observation step: k", "Task instruction: ...", the gripper state and the robot
self-geometry as one-line JSON, the executed actions as a JSON list); a repair turn repeats it
after the error message, so the same patterns apply.

Images: the active protocol sends one image per observation, from the view the agent's own
camera actions chose: the observation never names it, so it is read off the executed actions
(the last `camera.*` one; the head camera before any). The passive protocol sends five,
always in the order the system prompt lists (topdown, side, front_side_45, side_top_45,
oblique_45), all centred on the GC (the midpoint of both GCs in dual-arm tasks), and offers no
camera action.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

MEMO_MARK = " | memo "

_STEP = re.compile(r"^Observation step: (\d+)$", re.M)
_INSTRUCTION = re.compile(r"^Task instruction: (.*)$", re.M)
_GRIPPER = re.compile(r"^Gripper state: (\{.*\})$", re.M)
_GEOMETRY = re.compile(r"^Robot self-geometry[^\n]*\n(\{.*\})$", re.M)
_EXECUTED = re.compile(r"^Executed actions: (\[.*\])$", re.M)
_CAMERA_OFFERED = '{"action": "camera.'
HEAD_VIEW = "center_high"
_FENCE = re.compile(r"```json\s*(\{.*?\})\s*```", re.S)


class RequestError(ValueError):
    """The request does not carry an observation this agent can read."""


@dataclass(frozen=True)
class Arm:
    gc: np.ndarray
    rx: np.ndarray
    ry: np.ndarray
    rz: np.ndarray
    is_open: bool
    last_valid: bool | None
    last_planner: bool | None


PASSIVE_VIEWS = ("topdown", "side", "front_side_45", "side_top_45", "oblique_45")


@dataclass(frozen=True)
class Observation:
    step: int
    instruction: str
    view: str
    arms: dict[str, Arm]
    executed: int
    image: bytes | None
    """The image the agent locates objects in: the active protocol's one image, or the
    passive bundle's topdown image."""
    memo: dict[str, Any] = field(default_factory=dict)
    images: tuple[bytes, ...] = ()
    """Every image of the observation, in the order sent."""
    passive: bool = False

    @property
    def dual(self) -> bool:
        return len(self.arms) > 1

    def view_image(self, view: str) -> bytes | None:
        """The passive bundle's image of `view` (None in the active protocol)."""
        if not self.passive or len(self.images) != len(PASSIVE_VIEWS):
            return None
        return self.images[PASSIVE_VIEWS.index(view)]


def _arm(state: dict[str, Any], geometry: dict[str, Any], flags: dict[str, Any]) -> Arm:
    axes = geometry["local_axes_world"]
    return Arm(
        gc=np.array(state["finger_center_xyz"], float),
        rx=np.array(axes["rx"], float),
        ry=np.array(axes["ry"], float),
        rz=np.array(axes["rz"], float),
        is_open=bool(state["is_open"]),
        last_valid=flags.get("last_action_valid"),
        last_planner=flags.get("last_planner_success"),
    )


def _arms(state: dict[str, Any], geometry: dict[str, Any]) -> dict[str, Arm]:
    """Both blocks in the reference's shape: one arm's fields with `active_arm`, or
    `active_arm: "both"` with the arms under `left` and `right` (the flags at the top)."""
    if state.get("active_arm") == "both":
        return {a: _arm(state[a], geometry[a], state) for a in ("left", "right")}
    return {str(state["active_arm"]): _arm(state, geometry, state)}


def current_view(executed: list[Any], dual: bool) -> str:
    """The view the last camera action chose ("topdown"; in dual-arm tasks "both_side",
    "left_topdown", ...: the generic views centre on both arms), "adjusted" after a move, zoom
    or turn, the head camera's before any camera action: the camera stays where the last
    camera action put it."""
    for label in reversed(executed):
        if isinstance(label, str) and label.startswith("camera."):
            name = label.removeprefix("camera.")
            if not name.startswith("view_"):
                return "adjusted"
            view = name.removeprefix("view_")
            return f"both_{view}" if dual and view in PASSIVE_VIEWS else view
    return HEAD_VIEW


def parse_memo(reply: str) -> dict[str, Any]:
    """The memo of one of this agent's replies; {} for any other text."""
    m = _FENCE.search(reply)
    if not m:
        return {}
    try:
        reason = json.loads(m.group(1)).get("reason", "")
    except (json.JSONDecodeError, AttributeError):
        return {}
    if not isinstance(reason, str) or MEMO_MARK not in reason:
        return {}
    try:
        memo = json.loads(reason.rsplit(MEMO_MARK, 1)[1])
    except json.JSONDecodeError:
        return {}
    return memo if isinstance(memo, dict) else {}


def _text_and_images(turn: Any) -> tuple[str, tuple[bytes, ...]]:
    texts = [p for p in turn.content if isinstance(p, str)]
    images = tuple(p.data for p in turn.content if not isinstance(p, str))
    return "\n".join(texts), images


def parse_request(request: Any) -> Observation:
    """The observation of the last user turn and the memo of the last assistant turn of an
    `IncomingRequest` (read by attribute: `chat.turns[i].role/content`, image parts with
    `.data`); raises `RequestError` naming what is missing."""
    turns = list(request.chat.turns)
    users = [t for t in turns if t.role == "user"]
    if not users:
        raise RequestError("no user turn")
    text, images = _text_and_images(users[-1])
    step = _STEP.search(text)
    gripper = _GRIPPER.search(text)
    geometry = _GEOMETRY.search(text)
    if step is None or gripper is None or geometry is None:
        raise RequestError(
            "the last user turn has no observation (step line, gripper state, self-geometry)"
        )
    try:
        arms = _arms(json.loads(gripper.group(1)), json.loads(geometry.group(1)))
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise RequestError(f"robot state: {err}") from None
    assistants = [t for t in turns if t.role == "assistant"]
    memo = parse_memo(_text_and_images(assistants[-1])[0]) if assistants else {}
    instruction = _INSTRUCTION.search(text)
    executed_line = _EXECUTED.search(text)
    executed = json.loads(executed_line.group(1)) if executed_line else []
    passive = _CAMERA_OFFERED not in text
    return Observation(
        step=int(step.group(1)),
        instruction=instruction.group(1).strip() if instruction else "",
        # the passive bundle's first image is the one the agent locates in
        view="topdown" if passive else current_view(executed, len(arms) > 1),
        arms=arms,
        executed=len(executed),
        image=(images[0] if passive else images[-1]) if images else None,
        memo=memo,
        images=images,
        passive=passive,
    )
