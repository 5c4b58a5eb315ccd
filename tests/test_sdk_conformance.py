"""vabench's wire formats against the official `openai` and `anthropic` Python SDKs (test-only
dependencies, pinned in the `[test]` extra):

- the request bodies vabench sends, for all three APIs and every option it sends, are what the
  SDKs' parameter types describe (no unknown, missing or mistyped field, checked strictly by
  `sdk_types.problems`); the Anthropic headers are the ones the SDK sends;
- the SDK clients, pointed at the embedded server (real HTTP on loopback) with every parameter
  docs/LLM_POOL.md documents for it, complete their calls and parse the replies with strict
  response validation (`_strict_response_validation=True`: every required field present and
  typed); the server takes the Anthropic key as a bearer token and sends `request-id`;
- usage: cache-write tokens (OpenAI), thinking tokens (Anthropic); a reply without usage counts
  zero tokens with one warning per endpoint, not a retried format error.

The embedded server offers no streaming (`stream: true` is refused, naming the field), so none
is tested here.
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

import anthropic
import openai
import pytest
from aiohttp import web
from anthropic.types.message_create_params import MessageCreateParamsNonStreaming
from openai.types.chat.completion_create_params import CompletionCreateParamsNonStreaming
from openai.types.responses.response_create_params import ResponseCreateParamsNonStreaming
from sdk_types import problems

from vabench.llm_pool import ChatRequest, Image, LLMPool, Turn
from vabench.llm_pool.apis import ADAPTERS
from vabench.llm_pool.apis.anthropic import ANTHROPIC_VERSION
from vabench.llm_pool.apis.base import encode_body
from vabench.llm_pool.config import GenerationOptions, ModelEndpoint
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.llm_pool.tokens import stand_in_jpeg

KEY = "sk-conformance"
PARAMS = {
    "openai_chat": CompletionCreateParamsNonStreaming,
    "openai_responses": ResponseCreateParamsNonStreaming,
    "anthropic": MessageCreateParamsNonStreaming,
}
# Every option vabench sends, per API (docs/LLM_POOL.md, "Endpoint configuration").
OPTIONS = {
    "openai_chat": [
        GenerationOptions(),
        GenerationOptions(max_output_tokens=512, temperature=0.3, reasoning_effort="low"),
    ],
    "openai_responses": [
        GenerationOptions(),
        GenerationOptions(max_output_tokens=512, temperature=0.3, reasoning_effort="high"),
    ],
    "anthropic": [
        GenerationOptions(),
        GenerationOptions(max_output_tokens=4096, thinking_budget=1024),
        GenerationOptions(cache_prompt=False),
    ],
}


def conversation() -> ChatRequest:
    """What the engine sends: a system prompt, image observations, a reply, a five-view turn."""
    image = Image(stand_in_jpeg(64, 48))
    views = [part for v in ("topdown", "front", "left", "right", "back") for part in (v, image)]
    return ChatRequest(
        (
            Turn.user("Step 1/50 ...", image),
            Turn.assistant('```json\n{"action": "camera.view_topdown"}\n```'),
            Turn.user("Step 2/50 ...", *views),
        ),
        "You control a robot.",
    )


def wire_body(api: str, options: GenerationOptions, **endpoint: Any) -> dict[str, Any]:
    ep = ModelEndpoint(name="m", api=api, **endpoint)  # type: ignore[arg-type]
    return json.loads(encode_body(ADAPTERS[api].build_body(ep, conversation(), options)))


@pytest.mark.parametrize("api", sorted(PARAMS))
def test_request_bodies_are_what_the_sdk_parameter_types_describe(api):
    for options in OPTIONS[api]:
        assert problems(wire_body(api, options), PARAMS[api]) == [], options
    if api == "openai_chat":  # Ollama's field
        body = wire_body(api, GenerationOptions(), max_tokens_field="max_tokens")
        assert problems(body, PARAMS[api]) == []


def test_the_checker_catches_what_it_is_for():
    """A body with a parameter the API version dropped, a mistyped nested part and a missing
    required field is refused, each named (so the test above can fail)."""
    body = wire_body("anthropic", GenerationOptions())
    body["temperature"] = 0.5
    body["messages"][0]["content"][1]["source"]["type"] = "base64url"
    del body["max_tokens"]
    found = problems(body, PARAMS["anthropic"])
    assert any("body.temperature: not a parameter" in p for p in found), found
    assert any("messages.0.content.1" in p for p in found), found
    assert any("body.max_tokens: required" in p for p in found), found


async def _capture_headers(api: str, call) -> dict[str, str]:
    """The headers of one request `call(base_url)` sends, answered with a valid reply."""
    seen: dict[str, str] = {}
    reply = ADAPTERS[api].build_response(_server_reply())

    async def handle(request: web.Request) -> web.Response:
        seen.update({k.lower(): v for k, v in request.headers.items()})
        await request.read()
        return web.json_response(reply)

    app = web.Application()
    app.router.add_post(ADAPTERS[api].route, handle)
    runner = web.AppRunner(app)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = runner.addresses[0][1]
    try:
        await call(f"http://127.0.0.1:{port}")
    finally:
        await runner.cleanup()
    return seen


def _server_reply():
    from vabench.llm_pool.apis import ServerReply
    from vabench.llm_pool.messages import Usage

    return ServerReply("hi", "stop", Usage(input_tokens=10, output_tokens=2), "m")


def test_anthropic_headers_are_the_sdks():
    async def sdk(base_url: str) -> None:
        client = anthropic.AsyncAnthropic(api_key=KEY, base_url=base_url, max_retries=0)
        await client.messages.create(
            model="m", max_tokens=16, messages=[{"role": "user", "content": "hi"}]
        )
        await client.close()

    async def ours(base_url: str) -> None:
        endpoint = {"name": "m", "api": "anthropic", "base_url": base_url}
        async with LLMPool([{**endpoint, "api_key_env": "VABENCH_CONFORMANCE_KEY"}],
                           environ={"VABENCH_CONFORMANCE_KEY": KEY}) as pool:  # fmt: skip
            await pool.complete("m", ChatRequest([Turn.user("hi")]))

    theirs = asyncio.run(_capture_headers("anthropic", sdk))
    mine = asyncio.run(_capture_headers("anthropic", ours))
    for name in ("anthropic-version", "authorization", "content-type"):
        assert mine.get(name) == theirs.get(name), name
    assert mine["anthropic-version"] == ANTHROPIC_VERSION
    assert "x-api-key" not in mine and "x-api-key" not in theirs


@pytest.fixture
def server_config() -> ServerConfig:
    return ServerConfig(policy="echo", api_key=KEY, latency={"mean_s": 0.001})


def test_openai_sdk_chat_completions_against_the_embedded_server(server_config):
    async def main():
        async with LocalServer(server_config) as server:
            client = openai.AsyncOpenAI(
                api_key=KEY,
                base_url=server.base_url("openai_chat"),
                max_retries=0,
                _strict_response_validation=True,
            )
            image = Image(stand_in_jpeg(64, 48)).data_url
            content = [
                {"type": "text", "text": "Step 1"},
                {"type": "image_url", "image_url": {"url": image, "detail": "auto"}},
            ]
            messages = [
                {"role": "system", "content": "You control a robot."},
                {"role": "user", "content": content},
                {"role": "assistant", "content": "ok"},
                {"role": "user", "content": "Step 2"},
            ]
            plain = await client.chat.completions.create(model="m", messages=messages)
            full = await client.chat.completions.create(
                model="m",
                messages=messages,
                max_completion_tokens=256,
                temperature=0.2,
                top_p=0.9,
                stop=["\n\n\n"],
                seed=7,
                response_format={"type": "json_object"},
                reasoning_effort="low",
                user="vabench",
                n=1,
            )
            legacy = await client.chat.completions.with_raw_response.create(
                model="m", messages=messages, max_tokens=64
            )
            await client.close()
            return plain, full, legacy

    plain, full, legacy = asyncio.run(main())
    for reply in (plain, full, legacy.parse()):
        assert reply.choices[0].message.content and reply.usage is not None
        assert reply.usage.prompt_tokens > 0
        details = reply.usage.prompt_tokens_details
        assert details is not None and details.cache_write_tokens is not None
    assert full.usage.completion_tokens_details.reasoning_tokens > 0
    assert legacy.headers.get("x-request-id")


def test_openai_sdk_responses_against_the_embedded_server(server_config):
    async def main():
        async with LocalServer(server_config) as server:
            client = openai.AsyncOpenAI(
                api_key=KEY,
                base_url=server.base_url("openai_responses"),
                max_retries=0,
                _strict_response_validation=True,
            )
            image = Image(stand_in_jpeg(64, 48)).data_url
            items = [
                {
                    "role": "user",
                    "content": [
                        {"type": "input_text", "text": "Step 1"},
                        {"type": "input_image", "image_url": image, "detail": "auto"},
                    ],
                },
                {"role": "assistant", "content": "ok"},
                {"role": "user", "content": [{"type": "input_text", "text": "Step 2"}]},
            ]
            plain = await client.responses.create(model="m", input="Step 1")
            full = await client.responses.create(
                model="m",
                input=items,
                instructions="You control a robot.",
                max_output_tokens=2048,
                temperature=0.2,
                top_p=0.9,
                reasoning={"effort": "medium", "summary": "auto"},
                text={"format": {"type": "text"}},
                store=False,
                user="vabench",
            )
            await client.close()
            return plain, full

    plain, full = asyncio.run(main())
    for reply in (plain, full):
        assert reply.output_text and reply.usage is not None
        assert reply.usage.input_tokens_details.cache_write_tokens == 0
        assert reply.status == "completed" and reply.tools == []
    assert full.usage.output_tokens_details.reasoning_tokens > 0


@pytest.mark.parametrize("auth", ["api_key", "auth_token"])
def test_anthropic_sdk_messages_against_the_embedded_server(server_config, auth):
    async def main():
        async with LocalServer(server_config) as server:
            client = anthropic.AsyncAnthropic(
                **{auth: KEY},
                base_url=server.base_url("anthropic"),
                max_retries=0,
                _strict_response_validation=True,
            )
            image = Image(stand_in_jpeg(64, 48))
            source = {"type": "base64", "media_type": "image/jpeg", "data": image.b64}
            messages = [
                {
                    "role": "user",
                    "content": [
                        {"type": "text", "text": "Step 1"},
                        {"type": "image", "source": source, "cache_control": {"type": "ephemeral"}},
                    ],
                },
                {"role": "assistant", "content": "ok"},
                {"role": "user", "content": "Step 2"},
            ]
            cache = {"type": "ephemeral"}
            system = [{"type": "text", "text": "You control a robot.", "cache_control": cache}]
            replies = [
                await client.messages.create(model="m", max_tokens=64, messages=messages),
                await client.messages.create(
                    model="m",
                    max_tokens=2048,
                    messages=messages,
                    system=system,
                    stop_sequences=["\n\n\n"],
                    thinking={"type": "enabled", "budget_tokens": 1024},
                    metadata={"user_id": "vabench"},
                ),
                await client.messages.create(
                    model="m", max_tokens=64, messages=messages, thinking={"type": "adaptive"}
                ),
                await client.messages.create(
                    model="m", max_tokens=64, messages=messages, thinking={"type": "disabled"}
                ),
                # parameters of earlier API versions, still taken from their clients
                await client.messages.create(
                    model="m",
                    max_tokens=64,
                    messages=messages,
                    extra_body={"temperature": 0.2, "top_p": 0.9, "top_k": 40},
                ),
            ]
            await client.close()
            return replies

    replies = asyncio.run(main())
    for reply in replies:
        assert reply.content[-1].type == "text" and reply.content[-1].text
        assert reply.usage.input_tokens + (reply.usage.cache_read_input_tokens or 0) > 0
        assert reply._request_id and reply._request_id.startswith("req_")
    thinking = replies[1]
    assert thinking.content[0].type == "thinking"
    assert thinking.usage.output_tokens_details.thinking_tokens > 0


def test_streaming_is_refused_naming_the_field(server_config):
    async def main():
        async with LocalServer(server_config) as server:
            client = anthropic.AsyncAnthropic(
                api_key=KEY, base_url=server.base_url("anthropic"), max_retries=0
            )
            with pytest.raises(anthropic.BadRequestError) as err:
                await client.messages.create(
                    model="m", max_tokens=16, messages=[{"role": "user", "content": "hi"}],
                    stream=True,
                )  # fmt: skip
            await client.close()
            return err.value

    err = asyncio.run(main())
    assert "stream" in str(err)


# -- usage parsing ------------------------------------------------------------------------------


def usage_of(api: str, body: dict[str, Any]):
    return ADAPTERS[api].parse_response(json.dumps(body).encode()).usage


def test_cache_write_and_thinking_tokens_are_read():
    chat = usage_of(
        "openai_chat",
        {
            "choices": [{"message": {"content": "x"}, "finish_reason": "stop"}],
            "usage": {
                "prompt_tokens": 1000,
                "completion_tokens": 50,
                "prompt_tokens_details": {"cached_tokens": 600, "cache_write_tokens": 300},
                "completion_tokens_details": {"reasoning_tokens": 20},
            },
        },
    )
    assert (chat.input_tokens, chat.cached_input_tokens, chat.cache_write_tokens) == (100, 600, 300)
    assert (chat.output_tokens, chat.reasoning_tokens) == (50, 20)
    responses = usage_of(
        "openai_responses",
        {
            "output": [],
            "usage": {
                "input_tokens": 1000,
                "input_tokens_details": {"cached_tokens": 512, "cache_write_tokens": 256},
                "output_tokens": 10,
                "output_tokens_details": {"reasoning_tokens": 4},
            },
        },
    )
    assert (responses.input_tokens, responses.cache_write_tokens) == (232, 256)
    claude = usage_of(
        "anthropic",
        {
            "content": [{"type": "text", "text": "x"}],
            "usage": {
                "input_tokens": 10,
                "cache_creation_input_tokens": 2000,
                "cache_read_input_tokens": 3000,
                "output_tokens": 400,
                "output_tokens_details": {"thinking_tokens": 300},
            },
        },
    )
    assert (claude.cache_write_tokens, claude.cached_input_tokens) == (2000, 3000)
    assert (claude.output_tokens, claude.reasoning_tokens) == (400, 300)


@pytest.mark.parametrize("api", sorted(PARAMS))
def test_a_reply_without_usage_counts_zero_tokens_with_one_warning(api, caplog):
    """llama.cpp and other local servers omit usage at times: the reply is used, its tokens
    count as zero, and the endpoint warns once (before: a format error retried six times)."""
    body = ADAPTERS[api].build_response(_server_reply())
    del body["usage"]

    async def main():
        async def handle(request: web.Request) -> web.Response:
            await request.read()
            return web.json_response(body)

        app = web.Application()
        app.router.add_post(ADAPTERS[api].route, handle)
        runner = web.AppRunner(app)
        await runner.setup()
        await web.TCPSite(runner, "127.0.0.1", 0).start()
        port = runner.addresses[0][1]
        base = f"http://127.0.0.1:{port}" + ("" if api == "anthropic" else "/v1")
        try:
            async with LLMPool([{"name": "local", "api": api, "base_url": base}]) as pool:
                return [await pool.complete("local", ChatRequest([Turn.user("hi")])) for _ in "abc"]
        finally:
            await runner.cleanup()

    with caplog.at_level(logging.WARNING, logger="vabench.llm_pool"):
        results = asyncio.run(main())
    assert [r.text for r in results] == ["hi"] * 3
    assert all(r.attempts == 1 and r.usage.total_tokens == 0 for r in results)
    warnings = [r for r in caplog.records if "without usage" in r.getMessage()]
    assert len(warnings) == 1 and "local" in warnings[0].getMessage()
