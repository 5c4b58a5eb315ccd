"""The `reference_servo` policy: a reply to one request, from that request alone."""

from __future__ import annotations

import asyncio
import json
from typing import Any

from vabench.reference_agent.executor import decide
from vabench.reference_agent.families import family_of
from vabench.reference_agent.request import MEMO_MARK, RequestError, parse_request


def fenced(obj: dict[str, Any]) -> str:
    return f"```json\n{json.dumps(obj)}\n```"


SUMMARY_REPLY = (
    "Reference agent: nothing to summarise. Its plan and what it has seen are carried in the "
    "memo at the end of the reason of its latest reply."
)


def is_summary_request(request: Any) -> bool:
    """A history-compaction request: one user turn, text only (the earlier messages as text
    and an instruction to summarise them), no assistant turn."""
    turns = list(request.chat.turns)
    return len(turns) == 1 and all(isinstance(p, str) for p in turns[0].content)


def reply_text(request: Any) -> str:
    """The reply to an `IncomingRequest`, a pure function of it: one fenced JSON decision, or
    for a compaction request a short text (the memo, in the kept turns, is the agent's
    summary)."""
    if is_summary_request(request):
        return SUMMARY_REPLY
    try:
        obs = parse_request(request)
    except RequestError as err:
        return fenced({"stop": True, "reason": f"cannot read the observation: {err}"})
    family = family_of(obs.instruction, tuple(obs.arms))
    if family is None:
        return fenced({"stop": True, "reason": "no plan for this task"})
    action, reason, memo = decide(obs, family)
    text = reason + MEMO_MARK + json.dumps(memo, separators=(",", ":"))
    if action is None:
        return fenced({"stop": True, "reason": text})
    return fenced({**action, "reason": text})


class ReferenceServo:
    """Embedded-server policy (`make_policy("reference_servo")`): stateless, deterministic.

    The work (JPEG decoding, segmentation: tens of ms at 1280x960) runs in a worker thread so
    the server's event loop keeps answering the other episodes' calls meanwhile.
    """

    async def respond(self, request: Any) -> str:
        return await asyncio.to_thread(reply_text, request)
