"""Error replies read by what they mean, not only by their status, through real loopback HTTP:
a scripted aiohttp server answers as a LiteLLM proxy does (its bodies and headers as the real
proxy sends them, tests/test_gateway_litellm.py: a wrong key as `400 "No connected db."`, a
missing key as a bare text 500, an unknown model as a 400, a down upstream as a multi-line 500
"Connection error ... No fallback was attempted", an upstream's own 500 relayed with the same
ending, its own rate limit as a 429 whose wait is `llm_provider-retry-after`), and a server too
slow for the call's timeout. Each stops at its first attempt in one line naming the cause, or
(an upstream's 500, the 429s) is retried, the 429s without spending attempts.
"""

from __future__ import annotations

import asyncio
import json

import pytest
from aiohttp import web
from multidict import CIMultiDict

from vabench.llm_pool import ChatRequest, LLMPool, Turn
from vabench.llm_pool.apis.base import error_words
from vabench.llm_pool.errors import EndpointUnreachable, InfrastructureError, RequestRejected
from vabench.llm_pool.retry import meaning_of, server_retry_after

REQUEST = ChatRequest([Turn.user("ping")])
OK = {
    "id": "c1",
    "object": "chat.completion",
    "model": "m",
    "choices": [
        {
            "index": 0,
            "message": {"role": "assistant", "content": '{"stop": true}'},
            "finish_reason": "stop",
        }
    ],
    "usage": {"prompt_tokens": 5, "completion_tokens": 3, "total_tokens": 8},
}
NO_DB = {
    "error": {
        "message": "No connected db.",
        "type": "no_db_connection",
        "param": None,
        "code": "400",
    }
}
NO_KEY = "Internal Server Error"  # text/plain: the proxy's key check fails importing prisma
WRONG_MODEL = {
    "error": {
        "message": "/chat/completions: Invalid model name passed in model=gpt-x. Call "
        "`/v1/models` to view available models for your key.",
        "type": "invalid_request_error",
        "param": None,
        "code": "400",
    }
}
_RELAYED = "\n\nLiteLLM: model group 'm' failed with the error above. No fallback was attempted."
UPSTREAM_DOWN = {
    "error": {
        "message": "litellm.InternalServerError: InternalServerError: OpenAIException - "
        "Connection error." + _RELAYED,
        "type": "internal_server_error",
        "param": None,
        "code": "500",
    }
}
UPSTREAM_500 = {
    "error": {
        "message": "litellm.InternalServerError: InternalServerError: OpenAIException - "
        "injected fault: server_error" + _RELAYED,
        "type": "internal_server_error",
        "param": None,
        "code": "500",
    }
}
RATE = {
    "error": {
        "message": "litellm.RateLimitError: No deployments available for selected model. "
        "Passed model=m. Deployments={'c2644b': {'current_tpm': 22, 'tpm_limit': inf, "
        "'current_rpm': 1, 'rpm_limit': 2}}" + _RELAYED,
        "type": "throttling_error",
        "param": None,
        "code": "429",
    }
}


async def scripted(replies: list[tuple], delay_s: float = 0.0):
    """A server answering each POST with the next (status, body[, headers]) of `replies` (the
    last one repeated; a str body is sent as text/plain); returns (runner, base URL, the list
    of statuses sent)."""
    sent: list[int] = []

    async def handle(request: web.Request) -> web.Response:
        await request.read()
        status, body, *headers = replies[min(len(sent), len(replies) - 1)]
        sent.append(status)
        if delay_s:
            await asyncio.sleep(delay_s)
        if isinstance(body, str):
            return web.Response(status=status, text=body, headers=headers[0] if headers else None)
        return web.Response(
            status=status,
            text=json.dumps(body),
            content_type="application/json",
            headers=headers[0] if headers else None,
        )

    app = web.Application()
    app.router.add_post("/v1/chat/completions", handle)
    app.router.add_post("/v1/messages", handle)
    runner = web.AppRunner(app)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
    return runner, f"http://127.0.0.1:{port}/v1", sent


async def call(replies, api: str = "openai_chat", delay_s: float = 0.0, **endpoint):
    runner, url, sent = await scripted(replies, delay_s)
    model = {
        "name": "m",
        "api": api,
        "base_url": url if api == "openai_chat" else url.removesuffix("/v1"),
        "retry": {"max_attempts": 6, "backoff_base_s": 0.01, "backoff_max_s": 0.05},
        **endpoint,
    }
    try:
        async with LLMPool([model]) as pool:
            try:
                return await pool.complete("m", REQUEST), sent
            except Exception as err:
                return err, sent
    finally:
        await runner.cleanup()


@pytest.mark.parametrize(
    ("status", "body", "kind", "named"),
    [
        (400, NO_DB, "auth", "model 'm' has no api_key_env"),
        (500, NO_KEY, "auth", "model 'm' has no api_key_env: the endpoint wants a key"),
        (400, WRONG_MODEL, "not_found", "does not know the model 'm'"),
    ],
)
def test_a_key_or_model_problem_stops_at_the_first_attempt_naming_it(status, body, kind, named):
    err, sent = asyncio.run(call([(status, body)]))
    assert isinstance(err, RequestRejected) and err.fatal and err.kind == kind
    assert sent == [status] and err.attempts == 1  # no retries of a 500 that names the key
    assert named in f"{err} {err.hint}"
    assert "max_tokens_field" not in err.hint and "generation options" not in err.hint


def test_a_gateways_upstream_connection_error_is_an_unreachable_endpoint_in_one_line():
    err, sent = asyncio.run(call([(500, UPSTREAM_DOWN)]))
    assert isinstance(err, EndpointUnreachable) and sent == [500]
    assert "\n" not in str(err) and "No fallback was attempted" in str(err)
    assert "cannot reach the server behind it" in err.hint


def test_the_same_upstream_error_after_an_answer_is_retried():
    """Once the gateway has served the model, a down upstream is a passing outage."""

    async def main():
        runner, url, sent = await scripted([(200, OK), (500, UPSTREAM_DOWN), (200, OK)])
        model = {
            "name": "m",
            "api": "openai_chat",
            "base_url": url,
            "retry": {"backoff_base_s": 0.01},
        }
        try:
            async with LLMPool([model]) as pool:
                first = await pool.complete("m", REQUEST)
                second = await pool.complete("m", REQUEST)
                return first, second, sent
        finally:
            await runner.cleanup()

    first, second, sent = asyncio.run(main())
    assert sent == [200, 500, 200] and second.attempts == 2 and first.attempts == 1


def test_a_bare_500_to_a_call_with_a_key_is_retried_as_any_500(monkeypatch):
    """Only a call sent without a key reads a bare 500 as the key's problem."""
    monkeypatch.setenv("GATEWAY_KEY", "sk-test")
    quick = {"max_attempts": 2, "backoff_base_s": 0.01, "backoff_max_s": 0.05}
    err, sent = asyncio.run(call([(500, NO_KEY)], api_key_env="GATEWAY_KEY", retry=quick))
    assert isinstance(err, InfrastructureError) and sent == [500, 500], err


def test_an_upstreams_own_500_relayed_by_the_gateway_is_retried():
    """LiteLLM ends every relayed error with "No fallback was attempted": an upstream that
    answered with a 500 is reachable, so the call is retried (not an unreachable endpoint)."""
    result, sent = asyncio.run(call([(500, UPSTREAM_500), (200, OK)]))
    assert not isinstance(result, Exception), result
    assert sent == [500, 200] and result.attempts == 2


def test_the_gateways_relayed_wait_is_read_when_the_servers_own_headers_say_nothing():
    relayed = CIMultiDict(
        {"llm_provider-retry-after": "60", "llm_provider-retry-after-ms": "59604"}
    )
    assert server_retry_after(relayed) == pytest.approx(59.604)
    reset = CIMultiDict(
        {
            "llm_provider-x-ratelimit-remaining-requests": "0",
            "llm_provider-x-ratelimit-reset-requests": "2.5s",
        }
    )
    assert server_retry_after(reset) == pytest.approx(2.5)
    own = CIMultiDict({"Retry-After": "3", "llm_provider-retry-after": "60"})
    assert server_retry_after(own) == 3.0  # the answering server's own hint wins
    assert server_retry_after(CIMultiDict({"x-litellm-version": "1"})) is None


def test_a_gateways_429_waits_its_relayed_hint_and_spends_no_attempt():
    hint = {"llm_provider-retry-after-ms": "50", "llm_provider-retry-after": "1"}
    quick = {"max_attempts": 1, "backoff_base_s": 0.01, "backoff_max_s": 0.05}
    result, sent = asyncio.run(call([(429, RATE, hint), (200, OK)], retry=quick))
    assert not isinstance(result, Exception), result
    assert sent == [429, 200] and result.attempts == 2


def test_a_429_without_retry_after_waits_and_spends_no_attempt():
    """Three 429s with no hint, then an answer, with max_attempts 1: the waits are no
    failures (each longer than the last: the endpoint paused for every call)."""
    result, sent = asyncio.run(
        call(
            [(429, RATE), (429, RATE), (429, RATE), (200, OK)],
            retry={"max_attempts": 1, "backoff_base_s": 0.01, "backoff_max_s": 0.1},
        )
    )
    assert not isinstance(result, Exception), result
    assert sent == [429, 429, 429, 200] and result.attempts == 4  # HTTP attempts made


def test_a_400_of_the_anthropic_api_names_only_its_settings():
    body = {"type": "error", "error": {"type": "invalid_request_error", "message": "bad field"}}
    err, _ = asyncio.run(call([(400, body)], api="anthropic", generation={"max_output_tokens": 10}))
    assert isinstance(err, RequestRejected) and err.fatal
    assert "generation options" in err.hint and "max_tokens_field" not in err.hint
    err, _ = asyncio.run(call([(400, body)]))
    assert "max_tokens_field" in err.hint  # the field exists for OpenAI Chat only


def test_a_model_whose_every_call_times_out_stops_naming_the_model_and_the_timeout():
    err, sent = asyncio.run(
        call([(200, OK)], delay_s=2.0, retry={"request_timeout_s": 0.2, "backoff_base_s": 0.01})
    )
    assert isinstance(err, EndpointUnreachable), err
    assert "every call of model 'm' timed out after 0.2 s" in str(err)
    assert "retry.request_timeout_s" in err.hint and len(sent) == 2


@pytest.mark.parametrize(
    ("status", "text", "meaning"),
    [
        (400, "No connected db. auth_error", "key"),
        (401, "Incorrect API key provided", "key"),
        (404, "The model `gpt-9` does not exist or you do not have access to it.", "model"),
        (500, "Connection error. No fallback was attempted", "upstream"),
        (500, error_words(json.dumps(UPSTREAM_500).encode()), None),
        (429, error_words(json.dumps(RATE).encode()), None),
        (400, error_words(json.dumps(NO_DB).encode()), "key"),
        (400, error_words(json.dumps(WRONG_MODEL).encode()), "model"),
        (500, error_words(json.dumps(UPSTREAM_DOWN).encode()), "upstream"),
        (400, "max_tokens is too large: 100000", None),
        (500, "internal error", None),
        (400, "This model's maximum context length is 32768 tokens", None),
    ],
)
def test_meaning_of_error_texts(status, text, meaning):
    assert meaning_of(status, text) == meaning
