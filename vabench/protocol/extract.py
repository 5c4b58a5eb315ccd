"""The decision object of a model reply, found in free text, with reasoning kept apart.

Reasoning first (`split_reasoning`): reasoning models served without a reasoning parser leave
their thoughts in the answer, as `<think>...</think>` blocks, or, when the chat template
opened the block in the prompt, as text ending in a bare `</think>`. Those parts are reasoning,
never parsed for the decision: a fenced JSON draft inside the thinking is not the answer. An
unclosed `<think>` makes the rest of the reply reasoning (the model was cut off while
thinking, so there is no answer).

Then the answer is read as the benchmark's reference harness reads it (PROTOCOL_FACTS 3.2):

1. a fenced block, ```` ``` ```` or ```` ```json ```` (the tag in any case), whose body is
   `{...}`: the body runs lazily to the first `}` followed only by whitespace and the closing
   fence. The first such block is taken, except that a block that decodes to an object that
   is no decision (no "action", "tool", "tool_name" or "stop" key: a state the model quotes,
   an example) is passed over for the next one. If every block is passed over, the first is
   taken (its dispatch error says what is missing); a block that does not decode is an error,
   never a silent fall-back to another one.
2. otherwise the text from the first `{` to the last `}` is decoded; braces in the prose
   around the object therefore break it, as in the reference, and the repair text says so.
   (The reference decodes a reply that starts with `{` whole, so trailing prose fails there;
   here the slice rule applies to it too, which differs only when the prose after the object
   has no brace.)
"""

from __future__ import annotations

import json
import re
from typing import Any

from vabench.protocol.errors import REPLY, DecisionError

_FENCE = re.compile(r"```(?:json)?\s*(\{.*?\})\s*```", re.S | re.I)
_THINK_OPEN = re.compile(r"<think>", re.I)
_THINK_CLOSE = re.compile(r"</think>", re.I)
DECISION_KEYS = ("action", "tool", "tool_name", "stop")
"""The keys that make a JSON object a decision (an alias of "tool" included)."""


def split_reasoning(text: str) -> tuple[str, str | None]:
    """(answer, reasoning) of a reply whose reasoning may be inline (module docstring):
    `<think>` blocks anywhere and a leading text closed by a bare `</think>` are reasoning;
    an unclosed `<think>` makes the rest reasoning. Reasoning None when there is none."""
    thoughts: list[str] = []
    first_open = _THINK_OPEN.search(text)
    first_close = _THINK_CLOSE.search(text)
    if first_close is not None and (first_open is None or first_close.start() < first_open.start()):
        thoughts.append(text[: first_close.start()])
        text = text[first_close.end() :]
    answer: list[str] = []
    while (opening := _THINK_OPEN.search(text)) is not None:
        answer.append(text[: opening.start()])
        closing = _THINK_CLOSE.search(text, opening.end())
        if closing is None:
            thoughts.append(text[opening.end() :])
            text = ""
            break
        thoughts.append(text[opening.end() : closing.start()])
        text = text[closing.end() :]
    answer.append(text)
    reasoning = "\n".join(t.strip() for t in thoughts if t.strip())
    return "".join(answer).strip(), reasoning or None


def _decode(body: str, where: str) -> Any:
    try:
        return json.loads(body)
    except json.JSONDecodeError as err:
        raise DecisionError(
            REPLY, f"{where} is not valid JSON: {err.msg} at line {err.lineno} column {err.colno}"
        ) from None


def as_object(value: Any, where: str) -> dict[str, Any]:
    """`value` if it is a JSON object, else a `DecisionError` saying what it is."""
    if not isinstance(value, dict):
        kind = {list: "a list", str: "a string", bool: "a boolean", type(None): "null"}.get(
            type(value), "a number"
        )
        raise DecisionError(REPLY, f"{where} must be one JSON object, got {kind}")
    return value


def _plain_json(text: str) -> tuple[Any] | None:
    """(value,) if `text`, or the body of one fence around it, is JSON; None otherwise."""
    body = re.sub(r"^```[A-Za-z]*\s*|\s*```$", "", text)
    try:
        return (json.loads(body),)
    except json.JSONDecodeError:
        return None


def is_decision(value: Any) -> bool:
    """Whether a decoded value is an object with a decision key (`DECISION_KEYS`)."""
    return isinstance(value, dict) and any(k in value for k in DECISION_KEYS)


def extract_json_object(text: str) -> dict[str, Any]:
    """The decision object of a reply (module docstring); its reasoning is never read."""
    answer, _ = split_reasoning(text)
    if not answer:
        raise DecisionError(REPLY, "the reply is empty; reply with one JSON object")
    whole = _plain_json(answer)
    if whole is not None and not isinstance(whole[0], dict):
        return as_object(whole[0], "the reply")  # raises: say what the model sent
    bodies = [m[1] for m in _FENCE.finditer(answer)]
    if bodies:
        first = _decode(bodies[0], "the first ```json block")
        if not is_decision(first):
            for body in bodies[1:]:
                try:
                    value = json.loads(body)
                except json.JSONDecodeError:
                    continue
                if is_decision(value):
                    return value  # type: ignore[no-any-return]
        return as_object(first, "the first ```json block")
    start, end = answer.find("{"), answer.rfind("}")
    if start < 0 or end < start:
        if start >= 0:
            raise DecisionError(
                REPLY,
                "the reply has a '{' without a matching '}' (cut off?); reply with one JSON object",
            )
        raise DecisionError(REPLY, "no JSON object found in the reply; reply with one JSON object")
    try:
        value = json.loads(answer[start : end + 1])
    except json.JSONDecodeError as err:
        raise DecisionError(
            REPLY,
            "the text from the first '{' to the last '}' of the reply is not valid JSON "
            f"({err.msg} at line {err.lineno} column {err.colno}); reply with the JSON object "
            "alone, or in a ```json block, with no braces in the text around it",
        ) from None
    return as_object(value, "the reply")
