"""Endpoint configuration (errors name the field), API keys (from the environment, never in a
log or an error), the server's policies and its command line."""

from __future__ import annotations

import asyncio
import json
import logging
import re
import subprocess
import sys

import pytest
import yaml
from aiohttp import web

from vabench import protocol
from vabench.llm_pool import (
    ChatRequest,
    ConfigError,
    LLMPool,
    RequestRejected,
    Turn,
    load_endpoints,
)
from vabench.llm_pool.apis import IncomingRequest
from vabench.llm_pool.policies import POLICIES, make_policy, register_policy
from vabench.llm_pool.serve import build_parser, config_from_args
from vabench.llm_pool.server import LocalServer, ServerConfig

KEY = "sk-test-0123456789abcdef-secret"
REQUEST = ChatRequest([Turn.user("ping")])


def _model(**fields):
    return {"name": "m", "api": "openai_chat", **fields}


@pytest.mark.parametrize(
    "entry,field,words",
    [
        (_model(limits={"rpm": -1}), "models[0].limits.rpm", "must be more than 0.0, got -1"),
        (_model(limit={"rpm": 5}), "models[0].limit", "Extra inputs"),
        (_model(api="gemini"), "models[0].api", "openai_chat"),
        (_model(prices={"output": "cheap"}), "models[0].prices.output", "number"),
        (
            _model(generation={"thinking_budget": 2048}),
            "models[0].generation.thinking_budget",
            "anthropic only",
        ),
        (
            _model(api="anthropic", generation={"reasoning_effort": "high"}),
            "models[0].generation.reasoning_effort",
            "OpenAI only",
        ),
        (
            _model(api="anthropic", generation={"thinking_budget": 4096}),
            "models[0].generation.thinking_budget",
            "below max_output_tokens",
        ),
        (
            _model(api="anthropic", generation={"temperature": 0.2}),
            "models[0].generation.temperature",
            "takes no temperature",
        ),
        (
            _model(limits={"max_concurrency": 2, "min_concurrency": 4}),
            "models[0].limits",
            "min_concurrency",
        ),
        (_model(base_url="localhost:8000/v1"), "models[0].base_url", "http://"),
        (_model(name=""), "models[0].name", "at least 1 character"),
    ],
)
def test_config_errors_name_the_field(entry, field, words):
    with pytest.raises(ConfigError) as err:
        load_endpoints([entry])
    assert err.value.field == field
    assert words in str(err.value) and str(err.value).startswith(field)


def test_duplicate_names_are_rejected():
    with pytest.raises(ConfigError) as err:
        load_endpoints([_model(), _model(api="anthropic")])
    assert err.value.field == "models[1].name"


def test_a_sweep_models_list_loads_from_yaml():
    text = """
models:
  - name: gpt-x
    api: openai_responses
    api_key_env: OPENAI_API_KEY
    limits: {max_concurrency: 200, rpm: 5000, tpm: 2000000, adaptive: true}
    prices: {input: 1.25, cached_input: 0.125, output: 10}
    generation: {max_output_tokens: 4096, reasoning_effort: medium}
  - name: claude-x
    api: anthropic
    model: claude-sonnet-4-5
    api_key_env: ANTHROPIC_API_KEY
    prices: {input: 3, cached_input: 0.3, cache_write: 3.75, output: 15}
    generation: {max_output_tokens: 4096, thinking_budget: 1024}
  - name: local-qwen
    api: openai_chat
    base_url: http://localhost:8000/v1
    max_tokens_field: max_tokens
"""
    gpt, claude, local = load_endpoints(yaml.safe_load(text)["models"])
    assert gpt.limits.adaptive and gpt.generation.reasoning_effort == "medium"
    assert claude.provider_model == "claude-sonnet-4-5" and claude.prices.cache_write == 3.75
    assert local.resolved_base_url == "http://localhost:8000/v1" and local.api_key_env is None


def test_a_missing_key_stops_the_pool_before_any_call():
    with pytest.raises(ConfigError) as err:
        LLMPool([_model(api_key_env="VABENCH_NO_SUCH_KEY")], environ={})
    assert err.value.field == "models[0].api_key_env" and "VABENCH_NO_SUCH_KEY" in str(err.value)


@pytest.mark.parametrize("api", ["openai_chat", "openai_responses", "anthropic"])
def test_the_key_travels_in_the_api_header_and_nowhere_else(api, tmp_path, caplog):
    log_path = tmp_path / "requests.jsonl"

    async def main():
        config = ServerConfig(api_key=KEY, log_path=str(log_path), faults={"retry_after_s": 0})
        async with LocalServer(config) as server:
            server.faults.script("server_error")  # one retry, so the pool logs a failure
            endpoint = server.endpoint_config(
                "m", api, api_key_env="TEST_KEY", retry={"backoff_base_s": 0.01}
            )
            pool = LLMPool([endpoint], environ={"TEST_KEY": KEY})
            async with pool:
                result = await pool.complete("m", REQUEST)
                return result, repr(pool.endpoint("m")), repr(pool.endpoint("m").config)

    with caplog.at_level(logging.DEBUG, logger="vabench.llm_pool"):
        result, client_repr, config_repr = asyncio.run(main())
    assert result.attempts == 2  # the server accepted the key on the retry
    for text in (client_repr, config_repr, log_path.read_text(), caplog.text, str(result)):
        assert KEY not in text
    assert "server_error" in caplog.text


def test_a_key_echoed_by_a_provider_is_redacted():
    """Some providers repeat the key they were given in a 401; it must not reach a record."""

    async def echo_key(request: web.Request) -> web.Response:
        key = request.headers["Authorization"].removeprefix("Bearer ")
        body = {"error": {"message": f"Incorrect API key provided: {key}"}}
        return web.json_response(body, status=401)

    async def main():
        app = web.Application()
        app.router.add_post("/v1/chat/completions", echo_key)
        runner = web.AppRunner(app)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        port = runner.addresses[0][1]
        endpoint = _model(base_url=f"http://127.0.0.1:{port}/v1", api_key_env="K")
        try:
            async with LLMPool([endpoint], environ={"K": KEY}) as pool:
                with pytest.raises(RequestRejected) as err:
                    await pool.complete("m", REQUEST)
                return err.value
        finally:
            await runner.cleanup()

    err = asyncio.run(main())
    assert err.kind == "auth" and KEY not in str(err) and "[redacted]" in str(err)


# -- policies ---------------------------------------------------------------------------------


def _incoming(text: str) -> IncomingRequest:
    return IncomingRequest(api="openai_chat", model="m", chat=ChatRequest([Turn.user(text)]))


def _action(reply: str) -> dict:
    match = re.fullmatch(r"```json\n(.*)\n```", reply, flags=re.S)
    assert match, reply
    return json.loads(match.group(1))


@pytest.mark.parametrize(
    "prompt,arms",
    [
        ("Step 3/50. Available: gripper.move_world ...", ("right",)),
        ("Available: dual_gripper.move_world, left_gripper.open", ("left", "right")),
    ],
)
def test_random_actions_are_valid_protocol_actions(prompt, arms):
    policy = make_policy("random_action", seed=5)
    seen = set()
    for _ in range(400):
        action = _action(asyncio.run(policy.respond(_incoming(prompt))))
        parsed = protocol.parse_robot_action(action, arms)  # raises if invalid
        seen.add(type(parsed).__name__)
    expected = {"MoveWorld", "RotateLocal", "Aperture"} | ({"DualMove"} if len(arms) > 1 else set())
    assert seen == expected


def test_scripted_policy_replays_then_stops_or_cycles():
    async def replies(policy, n):
        return [await policy.respond(_incoming("x")) for _ in range(n)]

    cycling = make_policy("scripted", replies=["a", "b"], cycle=True)
    assert asyncio.run(replies(cycling, 5)) == ["a", "b", "a", "b", "a"]
    with pytest.raises(KeyError, match=r"valid policies: .*random_action"):
        make_policy("no_such_policy")
    with pytest.raises(ValueError, match="bad options"):
        make_policy("scripted", answers=["a"])
    with pytest.raises(ValueError, match="already registered"):
        register_policy("echo")(object)


def test_scripted_finish_reasons_and_max_tokens_reach_the_result():
    long_reply = "word " * 400

    async def main():
        replies = [{"text": "I cannot help.", "finish_reason": "refusal"}, long_reply]
        config = ServerConfig(policy="scripted", policy_options={"replies": replies})
        async with LocalServer(config) as server:
            endpoint = server.endpoint_config("m", "openai_responses")
            async with LLMPool([endpoint]) as pool:
                refusal = await pool.complete("m", REQUEST)
                short = ChatRequest([Turn.user("x")], options={"max_output_tokens": 20})
                cut = await pool.complete("m", short)
                return refusal, cut

    refusal, cut = asyncio.run(main())
    assert refusal.finish_reason == "refusal" and refusal.text == "I cannot help."
    assert cut.finish_reason == "length" and cut.usage.output_tokens == 20
    assert len(cut.text) < len(long_reply)


def test_policy_per_model_name():
    async def main():
        config = ServerConfig(
            policy="echo",
            model_policies={"script": {"policy": "scripted", "options": {"replies": ["s"]}}},
        )
        async with LocalServer(config) as server:
            endpoints = [
                server.endpoint_config("script", "anthropic"),
                server.endpoint_config("echo", "anthropic"),
            ]
            async with LLMPool(endpoints) as pool:
                return [(await pool.complete(n, REQUEST)).text for n in ("script", "echo")]

    assert asyncio.run(main()) == ["s", "ping [images: 0]"]
    assert {"random_action", "scripted", "echo"} <= set(POLICIES)


# -- the command line -------------------------------------------------------------------------


def test_cli_flags_build_a_server_config(tmp_path, monkeypatch):
    script = tmp_path / "replies.json"
    script.write_text(json.dumps(["a", "b"]))
    monkeypatch.setenv("SERVE_KEY", KEY)
    args = build_parser().parse_args(
        [
            "--script",
            str(script),
            "--latency",
            "2",
            "--latency-dist",
            "exponential",
            "--fault",
            "rate_limit=0.05",
            "--fault",
            "drop=0.01",
            "--retry-after",
            "3",
            "--rpm",
            "600",
            "--tpm",
            "100000",
            "--api-key-env",
            "SERVE_KEY",
        ]
    )
    config = config_from_args(args)
    assert config.policy == "scripted" and config.policy_options == {"replies": ["a", "b"]}
    assert config.latency.mean_s == 2 and config.latency.dist == "exponential"
    assert config.faults.rates == {"rate_limit": 0.05, "drop": 0.01}
    assert config.faults.retry_after_s == 3 and config.rpm == 600 and config.tpm == 100000
    assert config.api_key.get_secret_value() == KEY and KEY not in repr(config)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--fault", "meteor=0.5"])


def test_serve_runs_as_a_process():
    proc = subprocess.Popen(
        [sys.executable, "-m", "vabench.llm_pool.serve", "--port", "0", "--policy", "echo"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = proc.stdout.readline()
        url = re.search(r"http://[\d.]+:\d+", line).group(0)

        async def main():
            endpoint = {"name": "m", "api": "openai_chat", "base_url": f"{url}/v1"}
            async with LLMPool([endpoint]) as pool:
                return await pool.complete("m", REQUEST)

        assert asyncio.run(main()).text == "ping [images: 0]"
    finally:
        proc.terminate()
        assert proc.wait(timeout=10) == 0, proc.stderr.read()
