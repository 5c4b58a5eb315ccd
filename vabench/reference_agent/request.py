"""Reading a request: the latest observation (text and image) and the agent's own memo.

The agent keeps no state between requests. What it needs to remember (the plan it is
executing, where it saw the objects) it writes into the `reason` of each reply as
`... | memo {json}`; the conversation carries that reply back as the last assistant turn, so
the next request holds it. Only the last assistant turn is read, so history compaction (which
keeps the recent turns) never loses it.

The observation text is the one `vabench.agent.observation.render_observation` writes
("Step k of N ...", "Instruction: ...", "Current view: ...", the robot state JSON block); a
repair turn repeats it after the error message, so the same patterns apply.
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


@dataclass(frozen=True)
class Observation:
    step: int
    budget: int
    instruction: str
    view: str
    arms: dict[str, Arm]
    executed: int
    image: bytes | None
    memo: dict[str, Any] = field(default_factory=dict)

    @property
    def steps_left(self) -> int:
        return self.budget - self.step + 1


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


def _text_and_image(turn: Any) -> tuple[str, bytes | None]:
    texts = [p for p in turn.content if isinstance(p, str)]
    images = [p for p in turn.content if not isinstance(p, str)]
    return "\n".join(texts), (images[-1].data if images else None)


def parse_request(request: Any) -> Observation:
    """The observation of the last user turn and the memo of the last assistant turn of an
    `IncomingRequest` (read by attribute: `chat.turns[i].role/content`, image parts with
    `.data`); raises `RequestError` naming what is missing."""
    turns = list(request.chat.turns)
    users = [t for t in turns if t.role == "user"]
    if not users:
        raise RequestError("no user turn")
    text, image = _text_and_image(users[-1])
    step = _STEP.search(text)
    robot = _ROBOT.search(text)
    if step is None or robot is None:
        raise RequestError("the last user turn has no observation (step line, robot state)")
    try:
        arms = {name: _arm(f) for name, f in json.loads(robot.group(1)).items()}
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise RequestError(f"robot state: {err}") from None
    assistants = [t for t in turns if t.role == "assistant"]
    memo = parse_memo(_text_and_image(assistants[-1])[0]) if assistants else {}
    instruction = _INSTRUCTION.search(text)
    view = _VIEW.search(text)
    executed = _EXECUTED.search(text)
    return Observation(
        step=int(step.group(1)),
        budget=int(step.group(2)),
        instruction=instruction.group(1).strip() if instruction else "",
        view=view.group(1).strip() if view else "",
        arms=arms,
        executed=int(executed.group(1)) if executed else 0,
        image=image,
        memo=memo,
    )
