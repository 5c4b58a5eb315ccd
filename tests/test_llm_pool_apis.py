"""The three provider APIs: request bodies in each API's documented shape, two-image round trips
through the embedded server (which validates with models written from the docs), usage and cost
parsed the way each API counts, and documented example responses parsed."""

from __future__ import annotations

import asyncio
import json

import aiohttp
import pytest

from vabench.llm_pool import (
    ChatRequest,
    GenerationOptions,
    LLMPool,
    ModelEndpoint,
    Prices,
    RequestRejected,
    ResponseFormatError,
    Turn,
    Usage,
)
from vabench.llm_pool.apis import ADAPTERS, IncomingRequest
from vabench.llm_pool.apis.base import InlineImage, encode_body
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.llm_pool.testing import synthetic_image

APIS = ["openai_chat", "openai_responses", "anthropic"]
PRICES = {"input": 3.0, "cached_input": 0.3, "cache_write": 3.75, "output": 15.0}


class Capture:
    """A policy that remembers every request it answered."""

    def __init__(self):
        self.requests: list[IncomingRequest] = []

    async def respond(self, request: IncomingRequest) -> str:
        self.requests.append(request)
        return 'Moving down.\n```json\n{"action": "gripper.close"}\n```'


def conversation() -> ChatRequest:
    top = synthetic_image(1280, 960, size=20_000, seed=1)
    side = synthetic_image(640, 480, size=8_000, seed=2)
    return ChatRequest(
        system="You control a robot arm. " * 300,  # long enough to be cacheable
        turns=(
            Turn.user("Step 1/50. View: topdown", top),
            Turn.assistant('```json\n{"action": "gripper.open"}\n```'),
            Turn.user("Step 2/50. Views:", "topdown", top, "side", side),
        ),
    )


@pytest.mark.parametrize("api", APIS)
def test_two_images_round_trip_with_usage_and_cost(api):
    capture = Capture()
    request = conversation()

    async def main():
        async with LocalServer(policy=capture) as server:
            endpoint = server.endpoint_config("m", api, prices=PRICES)
            async with LLMPool([endpoint]) as pool:
                first = await pool.complete("m", request)
                second = await pool.complete("m", request)
                stats = pool.stats()["m"]
            return first, second, stats, list(server.log)

    first, second, stats, log = asyncio.run(main())
    # The server saw exactly what the client meant: same system, turns, text, image bytes.
    seen = capture.requests[0]
    assert seen.api == api and seen.model == "m"
    assert seen.chat.system == request.system
    assert seen.chat.turns == request.turns
    assert [im.data for im in seen.chat.turns[-1].images] == [
        im.data for im in request.turns[-1].images
    ]
    assert first.text.startswith("Moving down.") and first.finish_reason == "stop"
    assert first.attempts == 1 and first.latency_s > 0 and first.endpoint == "m"
    # Usage is what the server counted, split the same way for every API.
    assert first.usage.prompt_tokens == log[0].input_tokens
    assert first.usage.output_tokens == log[0].output_tokens
    prices = Prices(**PRICES)
    assert first.cost_usd == pytest.approx(first.usage.cost(prices))
    # The second identical call hits the (simulated) prompt cache and costs less.
    assert second.usage.cached_input_tokens > 0
    assert second.usage.prompt_tokens == first.usage.prompt_tokens
    assert second.cost_usd < first.cost_usd
    if api == "anthropic":
        assert first.usage.cache_write_tokens > 0 and first.usage.reasoning_tokens is None
        assert seen.cache_breakpoints  # markers arrived
    else:
        assert first.usage.cache_write_tokens == 0 and first.usage.reasoning_tokens == 0
    assert stats.usage == first.usage + second.usage
    assert stats.cost_usd == pytest.approx(first.cost_usd + second.cost_usd)


def _encoded(body: dict) -> dict:
    """The body as the server receives it (images are spliced in while encoding)."""
    return json.loads(encode_body(body))


def _b64(request: ChatRequest, turn: int, image: int) -> str:
    return request.turns[turn].images[image].b64


def test_openai_chat_body_shape():
    request = conversation()
    endpoint = ModelEndpoint(name="gpt", api="openai_chat", model="gpt-x")
    options = GenerationOptions(temperature=0.2, reasoning_effort="low")
    body = _encoded(ADAPTERS["openai_chat"].build_body(endpoint, request, options))
    url = "data:image/jpeg;base64,"
    assert body == {
        "model": "gpt-x",
        "messages": [
            {"role": "system", "content": request.system},
            {
                "role": "user",
                "content": [
                    {"type": "text", "text": "Step 1/50. View: topdown"},
                    {"type": "image_url", "image_url": {"url": url + _b64(request, 0, 0)}},
                ],
            },
            {"role": "assistant", "content": request.turns[1].text},
            {
                "role": "user",
                "content": [
                    {"type": "text", "text": "Step 2/50. Views:"},
                    {"type": "text", "text": "topdown"},
                    {"type": "image_url", "image_url": {"url": url + _b64(request, 2, 0)}},
                    {"type": "text", "text": "side"},
                    {"type": "image_url", "image_url": {"url": url + _b64(request, 2, 1)}},
                ],
            },
        ],
        "max_completion_tokens": 4096,
        "temperature": 0.2,
        "reasoning_effort": "low",
    }
    compat = endpoint.model_copy(update={"max_tokens_field": "max_tokens"})
    body = _encoded(ADAPTERS["openai_chat"].build_body(compat, request, GenerationOptions()))
    assert body["max_tokens"] == 4096 and "max_completion_tokens" not in body


def test_openai_responses_body_shape():
    request = conversation()
    endpoint = ModelEndpoint(name="gpt", api="openai_responses")
    options = GenerationOptions(max_output_tokens=1000, reasoning_effort="high")
    body = _encoded(ADAPTERS["openai_responses"].build_body(endpoint, request, options))
    url = "data:image/jpeg;base64,"
    assert body == {
        "model": "gpt",
        "instructions": request.system,
        "input": [
            {
                "role": "user",
                "content": [
                    {"type": "input_text", "text": "Step 1/50. View: topdown"},
                    {
                        "type": "input_image",
                        "image_url": url + _b64(request, 0, 0),
                        "detail": "auto",
                    },
                ],
            },
            {"role": "assistant", "content": request.turns[1].text},
            {
                "role": "user",
                "content": [
                    {"type": "input_text", "text": "Step 2/50. Views:"},
                    {"type": "input_text", "text": "topdown"},
                    {
                        "type": "input_image",
                        "image_url": url + _b64(request, 2, 0),
                        "detail": "auto",
                    },
                    {"type": "input_text", "text": "side"},
                    {
                        "type": "input_image",
                        "image_url": url + _b64(request, 2, 1),
                        "detail": "auto",
                    },
                ],
            },
        ],
        "max_output_tokens": 1000,
        "reasoning": {"effort": "high"},
        "store": False,
    }


def test_anthropic_body_shape_with_cache_markers_and_thinking():
    request = conversation()
    endpoint = ModelEndpoint(name="claude", api="anthropic")
    options = GenerationOptions(max_output_tokens=4096, thinking_budget=1024)
    body = _encoded(ADAPTERS["anthropic"].build_body(endpoint, request, options))

    def image(turn, i):
        data = _b64(request, turn, i)
        return {
            "type": "image",
            "source": {"type": "base64", "media_type": "image/jpeg", "data": data},
        }

    cache = {"type": "ephemeral"}
    assert body == {
        "model": "claude",
        "max_tokens": 4096,
        "system": [{"type": "text", "text": request.system, "cache_control": cache}],
        "messages": [
            {
                "role": "user",
                "content": [{"type": "text", "text": "Step 1/50. View: topdown"}, image(0, 0)],
            },
            {"role": "assistant", "content": request.turns[1].text},
            {
                "role": "user",
                "content": [
                    {"type": "text", "text": "Step 2/50. Views:"},
                    {"type": "text", "text": "topdown"},
                    image(2, 0),
                    {"type": "text", "text": "side"},
                    {**image(2, 1), "cache_control": cache},
                ],
            },
        ],
        "thinking": {"type": "enabled", "budget_tokens": 1024},
    }
    headers = ADAPTERS["anthropic"].headers("sk-test")
    # what the official SDK sends (tests/test_sdk_conformance.py checks it against the SDK)
    assert headers == {"anthropic-version": "2026-10-21", "Authorization": "Bearer sk-test"}
    plain = _encoded(
        ADAPTERS["anthropic"].build_body(endpoint, request, GenerationOptions(cache_prompt=False))
    )
    assert plain["system"] == request.system and "cache_control" not in json.dumps(plain)


@pytest.mark.parametrize("api", APIS)
def test_generation_options_reach_the_server(api):
    capture = Capture()
    if api == "anthropic":
        generation = {"max_output_tokens": 2048, "thinking_budget": 1024}
    else:
        generation = {"max_output_tokens": 2048, "temperature": 0.5, "reasoning_effort": "medium"}

    async def main():
        async with LocalServer(policy=capture) as server:
            endpoint = server.endpoint_config("m", api, generation=generation)
            async with LLMPool([endpoint]) as pool:
                return await pool.complete("m", ChatRequest([Turn.user("hi")]))

    result = asyncio.run(main())
    options = capture.requests[0].chat.options
    assert options is not None
    assert options.model_dump(exclude_none=True) == generation
    if api == "anthropic":
        assert result.reasoning  # the simulated thinking block was parsed
    else:
        assert result.usage.reasoning_tokens and result.usage.reasoning_tokens > 0


def test_request_overrides_endpoint_options():
    capture = Capture()

    async def main():
        async with LocalServer(policy=capture) as server:
            endpoint = server.endpoint_config("m", "openai_chat", generation={"temperature": 0.0})
            async with LLMPool([endpoint]) as pool:
                options = GenerationOptions(max_output_tokens=64)
                await pool.complete("m", ChatRequest([Turn.user("hi")], options=options))

    asyncio.run(main())
    options = capture.requests[0].chat.options
    assert options.temperature == 0.0 and options.max_output_tokens == 64


def test_documented_openai_chat_response_parses():
    raw = json.dumps(
        {
            "id": "chatcmpl-123",
            "object": "chat.completion",
            "created": 1677652288,
            "model": "gpt-4o-2024-08-06",
            "choices": [
                {
                    "index": 0,
                    "message": {"role": "assistant", "content": "Hello there"},
                    "logprobs": None,
                    "finish_reason": "length",
                }
            ],
            "usage": {
                "prompt_tokens": 2006,
                "completion_tokens": 300,
                "total_tokens": 2306,
                "prompt_tokens_details": {"cached_tokens": 1920, "audio_tokens": 0},
                "completion_tokens_details": {"reasoning_tokens": 128},
            },
        }
    ).encode()
    parsed = ADAPTERS["openai_chat"].parse_response(raw)
    assert parsed.text == "Hello there" and parsed.finish_reason == "length"
    # OpenAI counts cached tokens inside prompt_tokens: 2006 - 1920 are uncached.
    assert parsed.usage == Usage(86, 1920, 0, 300, 128)


def test_documented_openai_responses_response_parses():
    raw = json.dumps(
        {
            "id": "resp_1",
            "object": "response",
            "status": "incomplete",
            "incomplete_details": {"reason": "max_output_tokens"},
            "model": "o4-mini",
            "output": [
                {
                    "type": "reasoning",
                    "id": "rs_1",
                    "summary": [{"type": "summary_text", "text": "hm"}],
                },
                {
                    "type": "message",
                    "id": "msg_1",
                    "status": "completed",
                    "role": "assistant",
                    "content": [{"type": "output_text", "text": "Partial", "annotations": []}],
                },
            ],
            "usage": {
                "input_tokens": 1500,
                "input_tokens_details": {"cached_tokens": 1024},
                "output_tokens": 900,
                "output_tokens_details": {"reasoning_tokens": 800},
                "total_tokens": 2400,
            },
        }
    ).encode()
    parsed = ADAPTERS["openai_responses"].parse_response(raw)
    assert parsed.text == "Partial" and parsed.finish_reason == "length"
    assert parsed.reasoning == "hm"
    assert parsed.usage == Usage(476, 1024, 0, 900, 800)


def test_documented_anthropic_response_parses_and_costs():
    raw = json.dumps(
        {
            "id": "msg_01",
            "type": "message",
            "role": "assistant",
            "model": "claude-sonnet-4-5",
            "content": [
                {"type": "thinking", "thinking": "Let me look.", "signature": "abc"},
                {"type": "text", "text": "Closing the gripper."},
            ],
            "stop_reason": "end_turn",
            "stop_sequence": None,
            "usage": {
                "input_tokens": 50,
                "cache_creation_input_tokens": 248,
                "cache_read_input_tokens": 1800,
                "output_tokens": 503,
            },
        }
    ).encode()
    parsed = ADAPTERS["anthropic"].parse_response(raw)
    assert parsed.text == "Closing the gripper." and parsed.reasoning == "Let me look."
    # Anthropic counts cache reads and writes beside input_tokens, not inside.
    assert parsed.usage == Usage(50, 1800, 248, 503, None)
    assert parsed.usage.prompt_tokens == 2098
    cost = parsed.usage.cost(Prices(**PRICES))
    assert cost == pytest.approx((50 * 3 + 1800 * 0.3 + 248 * 3.75 + 503 * 15) / 1e6)


@pytest.mark.parametrize(
    "api,raw,problem",
    [
        ("openai_chat", b'{"id": "x", "choi', "invalid JSON"),
        (
            "openai_chat",
            b'{"choices": [], "usage": {"prompt_tokens": 1, "completion_tokens": 1}}',
            "field 'choices'",
        ),
        (
            "openai_responses",
            b'{"output": [], "usage": {"input_tokens": 1}}',
            "field 'usage.output_tokens'",
        ),
        (
            "anthropic",
            b'{"content": [{"type": "text", "text": "hi"}], "usage": {"input_tokens": 1}}',
            "field 'usage.output_tokens'",
        ),
        ("anthropic", b"", "empty body"),
    ],
)
def test_malformed_bodies_name_the_problem(api, raw, problem):
    with pytest.raises(ResponseFormatError, match=problem):
        ADAPTERS[api].parse_response(raw)


@pytest.mark.parametrize(
    "api,body,field",
    [
        (
            "openai_chat",
            {
                "model": "m",
                "messages": [
                    {
                        "role": "user",
                        "content": [
                            {"type": "image_url", "image_url": {"url": "https://example.com/a.jpg"}}
                        ],
                    }
                ],
            },
            "messages.0.content.0.image_url.url",
        ),
        (
            "openai_chat",
            {"model": "m", "messages": [{"role": "robot", "content": "hi"}]},
            "messages.0.role",
        ),
        (
            "openai_responses",
            {
                "model": "m",
                "input": [
                    {
                        "role": "user",
                        "content": [
                            {
                                "type": "input_image",
                                "image_url": {"url": "data:image/jpeg;base64,AAAA"},
                            }
                        ],
                    }
                ],
            },
            "input.0",
        ),
        (
            "anthropic",
            {"model": "m", "messages": [{"role": "user", "content": "hi"}]},
            "max_tokens",
        ),
        (
            "anthropic",
            {
                "model": "m",
                "max_tokens": 100,
                "thinking": {"type": "enabled", "budget_tokens": 2048},
                "messages": [{"role": "user", "content": "hi"}],
            },
            "thinking.budget_tokens",
        ),
    ],
)
def test_server_rejects_bad_shapes_naming_the_field(api, body, field):
    """A body that is not in the documented shape gets a 400 in the API's error format."""

    async def main():
        async with LocalServer() as server, aiohttp.ClientSession() as session:
            url = server.url + ADAPTERS[api].route
            headers = {"anthropic-version": "2023-06-01"}
            async with session.post(url, json=body, headers=headers) as resp:
                return resp.status, await resp.json()

    status, error = asyncio.run(main())
    assert status == 400
    assert field in error["error"]["message"]
    if api == "anthropic":
        assert error["type"] == "error" and error["error"]["type"] == "invalid_request_error"


def test_a_400_reaches_the_caller_as_request_rejected_with_the_message():
    async def main():
        config = ServerConfig(policy="scripted", policy_options={"replies": ["only one"]})
        async with LocalServer(config) as server:
            pool = LLMPool([server.endpoint_config("m", "anthropic")])
            async with pool:
                first = await pool.complete("m", ChatRequest([Turn.user("a")]))
                with pytest.raises(RequestRejected) as err:
                    await pool.complete("m", ChatRequest([Turn.user("b")]))
                return first, err.value

    first, err = asyncio.run(main())
    assert first.text == "only one"
    assert err.status == 400 and err.kind == "bad_request" and "exhausted" in str(err)


def test_encoded_bodies_splice_images_and_survive_the_marker_in_text():
    image = synthetic_image(size=3000, seed=9)
    marker_text = "\x1fvabench-inline-image\x1f"  # as if a prompt contained the marker
    for text in ("plain text", marker_text):
        body = {
            "a": [text, InlineImage(image, data_url=True)],
            "b": InlineImage(image, data_url=False),
        }
        decoded = json.loads(encode_body(body))
        assert decoded == {"a": [text, image.data_url], "b": image.b64}
