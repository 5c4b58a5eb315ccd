"""Reading a request: the latest observation (text and image) and the agent's own memo.

The agent keeps no state between requests. What it needs to remember (the plan it is
executing, where it saw the objects) it writes into the `reason` of each reply as
`... | memo {json}`; the conversation carries that reply back as the last assistant turn, so
the next request holds it. Only the last assistant turn is read, so history compaction (which
keeps the recent turns) never loses it.

The observation text is the one `vabench.agent.observation.render_observation` writes
("Step k of N ...", "Instruction: ...", "Current view: ...", the robot state JSON block); a
repair turn repeats it after the error message, so the same patterns apply.

Images: the active protocol sends one image per observation, from the view the "Current view"
line names; the passive protocol sends five, always in the order the system prompt and that
line list (topdown, side, front_side_45, side_top_45, oblique_45), all centred on the GC (the
midpoint of both GCs in dual-arm tasks).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

MEMO_MARK = " | memo "

_STEP = re.compile(r"Step (\d+) of (\d+)")
_INSTRUCTION = re.compile(r"^Instruction: (.*)$", re.M)
_VIEW = re.compile(r"^Current view: (.*)$", re.M)
_ROBOT = re.compile(r"Robot state[^\n]*\n```json\n(.*?)\n```", re.S)
_EXECUTED = re.compile(r"^Executed actions \((\d+)\):", re.M)
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
_PASSIVE_LINE = "the five fixed views"


@dataclass(frozen=True)
class Observation:
    step: int
    budget: int
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
    def steps_left(self) -> int:
        return self.budget - self.step + 1

    @property
    def dual(self) -> bool:
        return len(self.arms) > 1

    def view_image(self, view: str) -> bytes | None:
        """The passive bundle's image of `view` (None in the active protocol)."""
        if not self.passive or len(self.images) != len(PASSIVE_VIEWS):
            return None
        return self.images[PASSIVE_VIEWS.index(view)]


def _arm(fields: dict[str, Any]) -> Arm:
    axes = fields["local_axes_world"]
    return Arm(
        gc=np.array(fields["finger_center_xyz"], float),
        rx=np.array(axes["rx"], float),
        ry=np.array(axes["ry"], float),
        rz=np.array(axes["rz"], float),
        is_open=bool(fields["is_open"]),
        last_valid=fields.get("last_action_valid"),
        last_planner=fields.get("last_planner_success"),
    )


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
    robot = _ROBOT.search(text)
    if step is None or robot is None:
        raise RequestError("the last user turn has no observation (step line, robot state)")
    try:
        arms = {name: _arm(f) for name, f in json.loads(robot.group(1)).items()}
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise RequestError(f"robot state: {err}") from None
    assistants = [t for t in turns if t.role == "assistant"]
    memo = parse_memo(_text_and_images(assistants[-1])[0]) if assistants else {}
    instruction = _INSTRUCTION.search(text)
    view = _VIEW.search(text)
    view_name = view.group(1).strip() if view else ""
    executed = _EXECUTED.search(text)
    passive = view_name.startswith(_PASSIVE_LINE)
    if passive:
        view_name = "topdown"  # the bundle's first image is the one the agent locates in
    return Observation(
        step=int(step.group(1)),
        budget=int(step.group(2)),
        instruction=instruction.group(1).strip() if instruction else "",
        view=view_name,
        arms=arms,
        executed=int(executed.group(1)) if executed else 0,
        image=(images[0] if passive else images[-1]) if images else None,
        memo=memo,
        images=images,
        passive=passive,
    )
