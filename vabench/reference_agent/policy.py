"""The `reference_servo` policy: a reply to one request, from that request alone."""

from __future__ import annotations

import asyncio
import json
from typing import Any

from vabench.reference_agent.plans import decide, family_of
from vabench.reference_agent.request import MEMO_MARK, RequestError, parse_request


def fenced(obj: dict[str, Any]) -> str:
    return f"```json\n{json.dumps(obj)}\n```"


def reply_text(request: Any) -> str:
    """The reply (one fenced JSON decision) to an `IncomingRequest`: a pure function of it."""
    try:
        obs = parse_request(request)
    except RequestError as err:
        return fenced({"stop": True, "reason": f"cannot read the observation: {err}"})
    family = family_of(obs.instruction)
    if family is None or set(obs.arms) != {"right"}:
        return fenced({"stop": True, "reason": "no plan for this task (single right arm only)"})
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
