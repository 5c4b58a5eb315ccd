"""Response policies of the embedded server, registered by name.

A policy receives the full parsed request (system prompt, turns with text and images, the
generation options, which API it came through) and returns the reply text. Policies are what
make the embedded server a stand-in for a model: a random-but-valid actor for throughput runs,
a scripted one for tests that need exact replies, an echo for correlating calls. Later policies
(a non-LLM reference servo) register themselves the same way:

    @register_policy("reference_servo")
    class ReferenceServo: ...

`make_policy(name, **options)` builds one; an unknown name raises with the list of valid names.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import random
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol, get_args

from pydantic import BaseModel

from vabench import protocol
from vabench.llm_pool.apis.base import IncomingRequest
from vabench.llm_pool.messages import FinishReason


@dataclass(frozen=True)
class PolicyReply:
    """A reply with more than text: a finish reason other than "stop", or reasoning text; or
    `body`, a success body the server sends verbatim instead of its API's own shape (the
    shapes particular servers write: content as a list of parts, `reasoning` fields, tool
    calls); `text` then only feeds the simulated usage."""

    text: str = ""
    finish_reason: FinishReason = "stop"
    reasoning: str | None = None
    body: dict[str, Any] | None = None


class PolicyError(Exception):
    """A policy that cannot answer; the server replies with `status` and the message."""

    def __init__(self, message: str, status: int = 500):
        super().__init__(message)
        self.status = status


class Policy(Protocol):
    async def respond(self, request: IncomingRequest) -> str | PolicyReply: ...


PolicyFactory = Callable[..., Policy]
POLICIES: dict[str, PolicyFactory] = {}


def register_policy(name: str) -> Callable[[PolicyFactory], PolicyFactory]:
    def register(factory: PolicyFactory) -> PolicyFactory:
        if name in POLICIES:
            raise ValueError(f"policy {name!r} is already registered")
        POLICIES[name] = factory
        return factory

    return register


def make_policy(name: str, **options: Any) -> Policy:
    try:
        factory = POLICIES[name]
    except KeyError:
        raise KeyError(f"unknown policy {name!r}; valid policies: {sorted(POLICIES)}") from None
    try:
        return factory(**options)
    except TypeError as err:
        raise ValueError(f"policy {name!r}: bad options {sorted(options)}: {err}") from None


def fenced_json(obj: dict[str, Any]) -> str:
    """The reply shape the agent harness parses: one fenced json block."""
    return f"```json\n{json.dumps(obj)}\n```"


# -- random but valid robot actions ---------------------------------------------------------


def _choices(model: type[BaseModel], name: str) -> tuple[str, ...]:
    return get_args(model.model_fields[name].annotation)


def _bounds(model: type[BaseModel], name: str) -> tuple[int, int]:
    """The integer range of a numeric field, read from its Ge/Le constraints."""
    metadata = model.model_fields[name].metadata
    low = next((m.ge for m in metadata if hasattr(m, "ge")), None)
    high = next((m.le for m in metadata if hasattr(m, "le")), None)
    if low is None or high is None:
        raise TypeError(f"{model.__name__}.{name} has no ge/le bounds")
    return int(low), int(high)


# Read from vabench.protocol so that the policy follows the protocol when it changes.
_AXES = _choices(protocol.MoveWorld, "axis")
_ROT_AXES = _choices(protocol.RotateLocal, "axis")
_SIGNS = _choices(protocol.MoveWorld, "sign")
_DISTANCE = _bounds(protocol.MoveWorld, "distance_mm")
_ANGLE = _bounds(protocol.RotateLocal, "angle_deg")
_APERTURES = get_args(protocol.GripperName)
_SINGLE_APERTURES = tuple(a for a in _APERTURES if a.startswith("gripper."))
_DUAL_APERTURES = tuple(a for a in _APERTURES if not a.startswith("gripper."))


def learning_reply(request: IncomingRequest) -> str | None:
    """The stand-in models' side of a demonstration learning session (None outside one).

    Deterministic and stateless, from the conversation alone: list the frames, inspect the
    first, middle and last frame (of every video, when the first message lists several; at
    most `MAX_EXPERT_FRAMES` a call), then submit a generic summary built from the instruction
    (a real model writes what it saw). It passes the learning gate, so sweeps of the stand-ins
    run the whole protocol: learning stage, summaries in observations, records."""
    chat = request.chat
    if protocol.LEARNING_STAGE_MARK not in (chat.system or ""):
        return None
    first = next((t.text for t in chat.turns if t.role == "user"), "")
    replied = sum(t.role == "assistant" for t in chat.turns)
    if replied == 0:
        return fenced_json({"tool": "expert.retrieve", "args": {}})
    videos = [(int(a), int(b)) for a, b in re.findall(r"- video \d+, frames (\d+) to (\d+)", first)]
    if not videos:
        found = re.search(r"(\d+) frames", first)
        videos = [(0, int(found.group(1)) - 1 if found else 0)]
    wanted = sorted({k for a, b in videos for k in (a, (a + b) // 2, b)})
    per_call = protocol.MAX_EXPERT_FRAMES
    calls = [wanted[i : i + per_call] for i in range(0, len(wanted), per_call)]
    if replied <= len(calls):
        return fenced_json({"tool": "expert.frame", "args": {"steps": calls[replied - 1]}})
    instruction = re.search(r"Task instruction: (.*)", first)
    task = instruction.group(1).strip() if instruction else "the task"
    summary: dict[str, Any] = {
        "grasp_object_part": f"the object named in the instruction ({task})",
        "grasp_region": "the middle of the object, where it is narrowest across the fingers",
        "grasp_height_or_depth": "fingers reach about half the object's height",
        "finger_placement": "fingers on opposite sides, closing across the short axis",
        "approach_strategy": "move above the object, align, then descend vertically",
        "posture_or_rotation": "gripper pointing down, rotated so the fingers straddle it",
        "pre_close_checks": ["the object is between the fingers", "the fingers are low enough"],
        "test_lift_rule": "lift well clear of the table right after closing; the object rises",
        "safety_notes": f"a stand-in summary written by {request.model}",  # tells learners apart
    }
    if len(videos) > 1:
        summary["object_strategies"] = {
            kind: "grasp as its video shows, carry above the basket, release inside"
            for kind in ("cube", "horizontal bottle", "upright bottle", "pen")
        }
        summary["release_or_completion_rule"] = "done when all five objects rest in the basket"
    return fenced_json({"tool": "expert.learn", "args": summary})


@register_policy("random_action")
class RandomActionPolicy:
    """A uniformly random robot action that `vabench.protocol.parse_robot_action` accepts (and,
    in a demonstration learning session, `learning_reply`).

    `arms`: "right" (single-arm tasks), "both" (dual-arm tasks), or "auto": both when the
    request offers dual-arm actions (the observation's list of available actions mentions
    `dual_gripper`), else right.
    """

    def __init__(self, seed: int | None = None, arms: Literal["auto", "right", "both"] = "auto"):
        if arms not in ("auto", "right", "both"):
            raise ValueError(f"arms must be 'auto', 'right' or 'both', got {arms!r}")
        self.arms = arms
        self._rng = random.Random(seed)

    def _dual(self, request: IncomingRequest) -> bool:
        if self.arms != "auto":
            return self.arms == "both"
        chat = request.chat
        return "dual_gripper" in chat.last_user_text or "dual_gripper" in (chat.system or "")

    def _side(self) -> dict[str, Any]:
        rng = self._rng
        return {
            "axis": rng.choice(_AXES),
            "sign": rng.choice(_SIGNS),
            "distance_mm": rng.randint(*_DISTANCE),
        }

    def action(self, dual: bool) -> dict[str, Any]:
        rng = self._rng
        # The offered actions only: gripper.rotate_world is accepted, never offered.
        kinds = ["move", "rotate", "aperture"] + (["dual_move"] if dual else [])
        kind = rng.choice(kinds)
        arm = {"arm": rng.choice(("left", "right"))} if dual else {}
        if kind == "move":
            action = {"action": "gripper.move_world", **self._side(), **arm}
        elif kind == "rotate":
            angle = rng.randint(*_ANGLE)
            action = {
                "action": "gripper.rotate_local",
                "axis": rng.choice(_ROT_AXES),
                "sign": rng.choice(_SIGNS),
                "angle_deg": angle,
                **arm,
            }
        elif kind == "aperture":
            names = _SINGLE_APERTURES if not dual else _DUAL_APERTURES
            action = {"action": rng.choice(names)}
            if dual and action["action"].startswith("gripper."):
                action.update(arm)
        else:
            action = {
                "action": "dual_gripper.move_world",
                "left": self._side(),
                "right": self._side(),
            }
        action["reason"] = "random policy"
        return action

    async def respond(self, request: IncomingRequest) -> str:
        if (reply := learning_reply(request)) is not None:
            return reply
        return fenced_json(self.action(self._dual(request)))


@register_policy("scripted")
class ScriptedPolicy:
    """Replays `replies` in order, one per request, whatever the request says.

    A reply is a string or a mapping with `text` and optional `finish_reason` and `reasoning`,
    or with `body`, a whole success body sent verbatim (`PolicyReply`).
    Once the script is exhausted: start again if `cycle`, else answer 400 naming the problem
    (a test that runs past its script fails at once instead of retrying).
    """

    def __init__(self, replies: Sequence[str | dict[str, Any]], cycle: bool = False):
        if not replies:
            raise ValueError("scripted policy needs at least one reply")
        self.replies = [r if isinstance(r, str) else PolicyReply(**r) for r in replies]
        self.cycle = cycle
        self.served = 0

    async def respond(self, request: IncomingRequest) -> str | PolicyReply:
        if self.served >= len(self.replies) and not self.cycle:
            raise PolicyError(
                f"scripted policy exhausted after {len(self.replies)} replies", status=400
            )
        reply = self.replies[self.served % len(self.replies)]
        self.served += 1
        return reply


@register_policy("echo")
class EchoPolicy:
    """Replies with the text of the last user turn (and the number of images it carried), so
    a test can tell which call a reply belongs to."""

    async def respond(self, request: IncomingRequest) -> str:
        last = request.chat.turns[-1]
        return f"{last.text} [images: {len(last.images)}]"


@register_policy("conversation_hash")
class ConversationHashPolicy:
    """A random valid robot action drawn from a generator seeded by the conversation's text
    (system prompt and every turn's text, images excluded).

    Unlike `random_action`, whose draws follow the order in which requests arrive, each
    episode's replies here are a function of that episode's own conversation alone: concurrent
    episodes, interleavings and resumed sweeps get the same decisions. For reproducibility
    tests (a sweep killed and resumed must end as if it had run straight through).
    """

    def __init__(self, seed: int = 0, arms: Literal["auto", "right", "both"] = "auto"):
        self.seed = seed
        self.arms = arms

    async def respond(self, request: IncomingRequest) -> str:
        return conversation_hash_reply(request, self.seed, self.arms)


def conversation_hash_reply(
    request: IncomingRequest, seed: int = 0, arms: Literal["auto", "right", "both"] = "auto"
) -> str:
    """`conversation_hash`'s reply: a pure function of the request."""
    if (reply := learning_reply(request)) is not None:
        return reply
    chat = request.chat
    h = hashlib.sha256(f"{seed}\n{chat.system or ''}".encode())
    for turn in chat.turns:
        h.update(b"\x00" + turn.role.encode() + b"\x00" + turn.text.encode())
    actor = RandomActionPolicy(seed=int.from_bytes(h.digest()[:8], "big"), arms=arms)
    return fenced_json(actor.action(actor._dual(request)))


PURE_REPLIES: dict[str, str] = {
    "reference_servo": "vabench.reference_agent.policy:reply_text",
    "conversation_hash": "vabench.llm_pool.policies:conversation_hash_reply",
}
"""Stateless policies whose reply is a pure function `f(request, **options) -> str` that another
process can compute: the embedded server may run them in worker processes
(`ServerConfig.policy_processes`), so a CPU-heavy policy uses every core."""


def pure_reply(policy: str, options: dict[str, Any], request: IncomingRequest) -> str:
    """The reply of the pure policy `policy` (in a policy worker process)."""
    return pure_function(policy)(request, **options)


def pure_function(policy: str) -> Callable[..., str]:
    return _located(PURE_REPLIES[policy])


def _located(where: str) -> Any:
    """The object at "module:name", importing the module on first use."""
    module, _, name = where.partition(":")
    return getattr(importlib.import_module(module), name)


PLUGGED_POLICIES: dict[str, str] = {
    "reference_servo": "vabench.reference_agent:ReferenceServo",
    "rubric_judge": "vabench.diagnostics.judge_policy:RubricJudge",
}
"""Policies that live with what they stand in for: the non-LLM reference agent and the
behavioural diagnostics' stand-in judge (`vabench.diagnostics.judge`). They are named by where
they are and imported on first use, so that this package depends on neither (the diagnostics
sit above it) and importing it loads neither."""


def _plugged(where: str) -> PolicyFactory:
    def factory(**options: Any) -> Policy:
        return _located(where)(**options)

    return factory


for _name, _where in PLUGGED_POLICIES.items():
    POLICIES[_name] = _plugged(_where)
