"""A model's reply read as a decision, or named for what it is: the one reading the episode
engine and the learning session share.

The pool has already put every API's reply in one shape (`llm_pool.messages`): the answer
text, the reasoning apart, the finish reason, any function calls. Here, in this order:

1. a refusal (`finish_reason` "refusal": OpenAI's `refusal` field or Responses refusal part,
   Anthropic's `stop_reason: "refusal"`; also "content_filter", the provider declining for
   the model) is rejected as a refusal, whatever text came with it: a refused reply is never
   executed;
2. an answer text is parsed (`protocol.parse_decision`); if it holds no valid decision and the
   reply was cut at the output limit (`finish_reason` "length": OpenAI `length`, Responses
   `max_output_tokens`, Anthropic `max_tokens`) it is a truncation, else the parse error. A
   truncated reply that still holds a whole decision is that decision;
3. no answer text, but a function call (`tool_calls`, `function_call`, `tool_use`): vabench
   offers no tools, so this is a model writing its answer in the wrong channel. The
   benchmark's reference harness converts an Anthropic `tool_use` block into its decision
   (name "stop" is a stop, a tool's name that tool with the input as arguments, anything else
   an action named so with the input's fields merged; PROTOCOL_FACTS 3.3); the same is done
   here for every API's first call. A call that converts into no valid decision is rejected
   with "answer in text, not a function call";
4. no answer text, cut at the output limit (the model spent it all on reasoning): truncation;
5. no answer text but reasoning: the answer came in the reasoning channel only (reasoning is
   never parsed for the decision);
6. nothing at all: an empty reply.

Every rejection is a `ReplyRejected` whose `kind` names it and whose text is the repair sent
back; the engine counts them (`refusals`, `truncations`, `empty_replies`: cases 5 and 6) and,
when the repairs of a decision run out, ends the episode with the last rejection's stop reason
(`stop_reason_of`): `refused`, `truncated` or `invalid_output`, all scored failures.
"""

from __future__ import annotations

import json
from typing import Any, Literal

from vabench import protocol as P
from vabench.llm_pool.messages import CompletionResult, FunctionCall

RejectionKind = Literal[
    "refusal", "truncation", "function_call", "reasoning_only", "empty", "invalid"
]
_STOP_REASONS = {"refusal": "refused", "truncation": "truncated"}


class ReplyRejected(Exception):
    """A reply that is no decision: `kind` names what it was, `field` the offending field
    (`protocol.REPLY` for the reply as a whole), `str(self)` the repair text."""

    def __init__(self, kind: RejectionKind, field: str, message: str):
        super().__init__(message)
        self.kind: RejectionKind = kind
        self.field = field

    @property
    def empty(self) -> bool:
        """No answer text at all (counted in `empty_replies`)."""
        return self.kind in ("reasoning_only", "empty")


def stop_reason_of(kind: RejectionKind) -> str:
    """The stop reason of an episode whose repairs ran out on a rejection of `kind`."""
    return _STOP_REASONS.get(kind, "invalid_output")


def truncation_message(output_limit: int) -> str:
    return (
        f"your reply was cut off at the output limit ({output_limit} tokens): reply with the "
        "JSON object only"
    )


def function_call_object(call: FunctionCall) -> dict[str, Any]:
    """The decision object of a function call, converted as the reference converts a
    `tool_use` block (module docstring); `DecisionError` if its arguments are no object."""
    args: Any = call.arguments
    if isinstance(args, str):
        try:
            args = json.loads(args) if args.strip() else {}
        except json.JSONDecodeError as err:
            raise P.DecisionError("arguments", f"not valid JSON: {err.msg}") from None
    if not isinstance(args, dict):
        raise P.DecisionError("arguments", "must be a JSON object")
    if call.name == "stop":
        return {"stop": True, **args}
    if call.name in P.TOOL_NAMES:
        return {"tool": call.name, "args": args}
    return {"action": call.name, **args}


def read_decision(
    result: CompletionResult, ctx: P.DecisionContext, output_limit: int
) -> P.Decision:
    """The decision of one reply, or `ReplyRejected` (module docstring). `output_limit` is the
    call's max output tokens, quoted in the truncation repair."""
    if result.finish_reason in ("refusal", "content_filter"):
        said = " ".join(result.text.split())[:200]
        why = f" ({said})" if said else ""
        raise ReplyRejected(
            "refusal",
            P.REPLY,
            f"your reply was a refusal{why}. This is a simulated robot in a benchmark scene, "
            "with no real-world effect: reply with one JSON decision (an action, a tool call, "
            'or {"stop": true} to end the episode)',
        )
    truncated = result.finish_reason == "length"
    if result.text.strip():
        try:
            return P.parse_decision(result.text, ctx)
        except P.DecisionError as err:
            if truncated:
                raise ReplyRejected(
                    "truncation", P.REPLY, truncation_message(output_limit)
                ) from None
            raise ReplyRejected("invalid", err.field, str(err)) from None
    if result.function_calls:
        call = result.function_calls[0]
        try:
            return P.decision_from_object(function_call_object(call), ctx)
        except P.DecisionError as err:
            raise ReplyRejected(
                "function_call",
                err.field,
                f"answer in text, not a function call (the reply called {call.name!r}): reply "
                f"with the JSON object as the text of your message; {err}",
            ) from None
    if truncated:
        raise ReplyRejected("truncation", P.REPLY, truncation_message(output_limit))
    if result.reasoning:
        raise ReplyRejected(
            "reasoning_only",
            P.REPLY,
            "your answer came in the reasoning channel only: put the JSON object in the reply",
        )
    raise ReplyRejected("empty", P.REPLY, "the reply is empty: reply with one JSON object")


def history_text(result: CompletionResult) -> str:
    """The reply as the conversation keeps it: the answer text, or a function call written as
    its JSON object, so that the next turn sees what the model did."""
    if result.text.strip() or not result.function_calls:
        return result.text
    call = result.function_calls[0]
    args = call.arguments if isinstance(call.arguments, str) else json.dumps(call.arguments)
    return f"[function call {call.name}({args})]"
