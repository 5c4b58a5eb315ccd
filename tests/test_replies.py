"""Replies as real models and servers write them, read through the real HTTP path: the
embedded server sends each body verbatim (a scripted policy's `PolicyReply.body`), the pool
reads it with the API's adapter, and `agent.replies.read_decision` turns it into a decision
or a named rejection with the repair text the model gets."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest

from vabench import protocol as P
from vabench.agent.replies import ReplyRejected, read_decision
from vabench.llm_pool.messages import ChatRequest, CompletionResult, Turn
from vabench.llm_pool.policies import ScriptedPolicy
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer

CTX = P.DecisionContext(("right",))
LIMIT = 512
OPEN = {"action": "gripper.open"}
CLOSE = {"action": "gripper.close"}


def fence(obj: dict[str, Any]) -> str:
    return f"```json\n{json.dumps(obj)}\n```"


async def _complete(api: str, body: dict[str, Any]) -> CompletionResult:
    policy = ScriptedPolicy([{"body": body}])
    async with LocalServer(policy=policy) as server:
        endpoint = server.endpoint_config("m", api, generation={"max_output_tokens": LIMIT})
        async with LLMPool([endpoint]) as llm:
            return await llm.complete("m", ChatRequest((Turn.user("observe"),)))


def served(api: str, body: dict[str, Any]) -> CompletionResult:
    return asyncio.run(_complete(api, body))


def decided(api: str, body: dict[str, Any]) -> P.Decision:
    return read_decision(served(api, body), CTX, LIMIT)


def rejected(api: str, body: dict[str, Any]) -> ReplyRejected:
    with pytest.raises(ReplyRejected) as e:
        decided(api, body)
    return e.value


# -- OpenAI Chat Completions and compatible servers -------------------------------------------


def chat(message: dict[str, Any], finish: str = "stop") -> dict[str, Any]:
    return {
        "id": "chatcmpl-1",
        "model": "m",
        "choices": [
            {"index": 0, "message": {"role": "assistant", **message}, "finish_reason": finish}
        ],
        "usage": {"prompt_tokens": 10, "completion_tokens": 5},
    }


def test_chat_content_as_a_list_of_text_parts_is_joined():
    parts = [
        {"type": "text", "text": "```json\n"},
        {"type": "text", "text": json.dumps(CLOSE) + "\n```"},
    ]
    result = served("openai_chat", chat({"content": parts}))
    assert result.text == fence(CLOSE)
    assert read_decision(result, CTX, LIMIT).action == "gripper.close"


@pytest.mark.parametrize(
    "content",
    [
        # a reasoning model served without a reasoning parser: its thoughts stay in content
        f"<think>a draft:\n{fence(OPEN)}\nno, close instead</think>\n{json.dumps(CLOSE)}",
        # the chat template opened <think> in the prompt: the reply starts inside it
        f"a draft:\n{fence(OPEN)}\nno, close instead\n</think>\n\n{json.dumps(CLOSE)}",
    ],
)
def test_inline_thinking_is_reasoning_and_its_draft_is_never_executed(content):
    result = served("openai_chat", chat({"content": content}))
    assert result.text == json.dumps(CLOSE)
    assert result.reasoning is not None and "a draft" in result.reasoning
    assert read_decision(result, CTX, LIMIT).action == "gripper.close"


@pytest.mark.parametrize("field", ["reasoning_content", "reasoning"])
def test_reasoning_fields_are_kept_apart(field):
    result = served("openai_chat", chat({"content": fence(CLOSE), field: f"think {fence(OPEN)}"}))
    assert result.reasoning == f"think {fence(OPEN)}"
    assert read_decision(result, CTX, LIMIT).action == "gripper.close"


@pytest.mark.parametrize("field", ["reasoning_content", "reasoning"])
def test_an_answer_in_the_reasoning_channel_only_is_named(field):
    err = rejected("openai_chat", chat({"content": None, field: fence(OPEN)}))
    assert (err.kind, err.empty) == ("reasoning_only", True)
    assert str(err) == (
        "your answer came in the reasoning channel only: put the JSON object in the reply"
    )


def test_an_empty_reply_is_named():
    err = rejected("openai_chat", chat({"content": ""}))
    assert (err.kind, err.empty) == ("empty", True)


def test_a_refusal_field_is_a_refusal_even_with_json_beside_it():
    err = rejected("openai_chat", chat({"content": None, "refusal": "I can't help with that."}))
    assert err.kind == "refusal" and "refusal (I can't help with that.)" in str(err)
    assert rejected("openai_chat", chat({"content": fence(OPEN)}, "content_filter")).kind == (
        "refusal"
    )


def test_a_reply_cut_at_the_output_limit_is_a_truncation():
    err = rejected("openai_chat", chat({"content": 'I will now {"action": "gripper.mo'}, "length"))
    assert err.kind == "truncation"
    assert str(err) == (
        f"your reply was cut off at the output limit ({LIMIT} tokens): reply with the JSON "
        "object only"
    )
    # cut after a whole decision: that decision
    body = chat({"content": fence(CLOSE) + "\nbecause the cube is between the"}, "length")
    assert decided("openai_chat", body).action == "gripper.close"
    # cut while reasoning: nothing but reasoning, at the limit
    body = chat({"content": None, "reasoning_content": "let me think about"}, "length")
    assert rejected("openai_chat", body).kind == "truncation"


def test_tool_calls_convert_as_the_reference_converts_them():
    call = {
        "id": "call_1",
        "type": "function",
        "function": {
            "name": "gripper.move_world",
            "arguments": json.dumps({"axis": "Z", "sign": "cw", "distance_mm": 20}),
        },
    }
    d = decided("openai_chat", chat({"content": None, "tool_calls": [call]}, "tool_calls"))
    assert P.decision_label(d) == "move_world z-20mm"
    stop = {"type": "function", "function": {"name": "stop", "arguments": "{}"}}
    assert isinstance(decided("openai_chat", chat({"tool_calls": [stop]})), P.Stop)


def test_a_function_call_that_is_no_decision_is_told_to_answer_in_text():
    call = {"type": "function", "function": {"name": "move_arm", "arguments": '{"x": 1}'}}
    err = rejected("openai_chat", chat({"content": None, "tool_calls": [call]}, "tool_calls"))
    assert err.kind == "function_call"
    assert str(err).startswith("answer in text, not a function call")


def test_null_optional_fields_and_upper_case_axes():
    body = chat({"content": json.dumps({**OPEN, "tool": None, "args": None})})
    assert decided("openai_chat", body).action == "gripper.open"
    move = {"action": "gripper.move_world", "axis": "X", "sign": "+", "distance_mm": 5}
    assert decided("openai_chat", chat({"content": json.dumps(move)})).axis == "x"


# -- Anthropic Messages -----------------------------------------------------------------------


def messages(content: list[dict[str, Any]], stop_reason: str = "end_turn") -> dict[str, Any]:
    return {
        "id": "msg_1",
        "type": "message",
        "role": "assistant",
        "model": "m",
        "content": content,
        "stop_reason": stop_reason,
        "usage": {"input_tokens": 10, "output_tokens": 5},
    }


def test_anthropic_thinking_blocks_are_reasoning():
    body = messages(
        [
            {"type": "thinking", "thinking": f"draft {fence(OPEN)}", "signature": "s"},
            {"type": "text", "text": "Closing now.\n"},
            {"type": "text", "text": fence(CLOSE)},
        ]
    )
    result = served("anthropic", body)
    assert result.reasoning == f"draft {fence(OPEN)}"
    assert read_decision(result, CTX, LIMIT).action == "gripper.close"


def test_anthropic_redacted_thinking_alone_is_an_answer_in_the_reasoning_channel():
    body = messages([{"type": "redacted_thinking", "data": "xyz"}])
    assert rejected("anthropic", body).kind == "reasoning_only"


def test_anthropic_refusal_and_max_tokens_are_named():
    assert rejected("anthropic", messages([{"type": "text", "text": "I"}], "refusal")).kind == (
        "refusal"
    )
    cut = messages([{"type": "text", "text": '{"action": "gripp'}], "max_tokens")
    assert rejected("anthropic", cut).kind == "truncation"


def test_anthropic_tool_use_converts_as_the_reference_converts_it():
    body = messages(
        [{"type": "tool_use", "id": "t1", "name": "camera.history", "input": {"step": 0}}],
        "tool_use",
    )
    d = decided("anthropic", body)
    assert P.decision_label(d) == "tool camera.history step=0"


# -- OpenAI Responses -------------------------------------------------------------------------


def responses(output: list[dict[str, Any]], **fields: Any) -> dict[str, Any]:
    return {
        "id": "resp_1",
        "model": "m",
        "status": "completed",
        "output": output,
        "usage": {"input_tokens": 10, "output_tokens": 5},
        **fields,
    }


def test_responses_reasoning_text_and_function_call_items():
    reasoning = {
        "type": "reasoning",
        "summary": [],
        "content": [{"type": "reasoning_text", "text": f"draft {fence(OPEN)}"}],
    }
    answer = {"type": "message", "content": [{"type": "output_text", "text": fence(CLOSE)}]}
    result = served("openai_responses", responses([reasoning, answer]))
    assert result.reasoning == f"draft {fence(OPEN)}"
    assert read_decision(result, CTX, LIMIT).action == "gripper.close"
    call = {"type": "function_call", "name": "gripper.close", "arguments": "{}"}
    assert decided("openai_responses", responses([reasoning, call])).action == "gripper.close"
    cut = responses(
        [reasoning], status="incomplete", incomplete_details={"reason": "max_output_tokens"}
    )
    assert rejected("openai_responses", cut).kind == "truncation"
