"""One registration per model API: `apis.ADAPTERS` is the only list of the APIs,
and the config schema, the pool, the embedded server, its prompt-cache simulation and the
dry-run's estimate all derive from it. A fake API registered in one test shows up in every one
of them; a source scan fails on any module that names the APIs by hand instead (a per-API
mapping, a Literal of API names, a comparison with an API's name).
"""

from __future__ import annotations

import ast
import asyncio
from pathlib import Path
from typing import get_args

import pytest

import vabench
from vabench.agent.usage import Assumptions, episode_usage
from vabench.llm_pool import ChatRequest, GenerationOptions, LLMPool, Turn
from vabench.llm_pool.apis import ADAPTERS, get_adapter
from vabench.llm_pool.apis.base import ApiAdapter
from vabench.llm_pool.apis.openai_chat import OpenAIChat
from vabench.llm_pool.config import ApiName, ConfigError, ModelEndpoint, load_endpoint
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.llm_pool.testing import synthetic_image
from vabench.llm_pool.tokens import openai_image_tokens

ROOT = Path(vabench.__file__).parent
REGISTRY_DIR = ROOT / "llm_pool" / "apis"
BENCHMARKS = ROOT.parent / "benchmarks"


def _adapter_classes(cls: type = ApiAdapter) -> set[type]:
    """Every concrete adapter class vabench defines (tests' fakes left out)."""
    found = set()
    for sub in cls.__subclasses__():
        found |= _adapter_classes(sub)
        if not getattr(sub, "__abstractmethods__", None) and sub.__module__.startswith("vabench."):
            found.add(sub)
    return found


def test_every_adapter_is_registered_once_under_its_name_and_route():
    assert {type(a) for a in ADAPTERS.values()} == _adapter_classes()
    assert len(ADAPTERS) == len(_adapter_classes())  # no two share a name
    assert all(name == adapter.name for name, adapter in ADAPTERS.items())
    routes = [a.route for a in ADAPTERS.values()]
    assert len(set(routes)) == len(routes), "two APIs cannot share the server's route"


def test_the_config_schema_takes_exactly_the_registered_apis():
    assert get_args(ApiName) == tuple(ADAPTERS)
    assert ModelEndpoint.model_fields["api"].annotation == ApiName
    with pytest.raises(ConfigError) as err:
        load_endpoint({"name": "m", "api": "no_such_api"}, where="models[0]")
    assert err.value.field == "models[0].api"
    assert all(repr(name) in err.value.message for name in ADAPTERS)
    for name, adapter in ADAPTERS.items():
        endpoint = ModelEndpoint(name="m", api=name)
        assert endpoint.resolved_base_url == adapter.default_base_url


def test_the_embedded_server_serves_exactly_the_registered_routes():
    posts = {
        r.resource.canonical
        for r in LocalServer().app().router.routes()
        if r.method == "POST" and r.resource is not None
    }
    assert posts == {a.route for a in ADAPTERS.values()}


class FakeApi(OpenAIChat):
    """An API that exists only in this test: OpenAI-shaped bodies at its own route and host,
    with its own image rule, option check and prompt caching, each one noticeable."""

    name = "fake_api"
    route = "/v1/fake/chat"
    default_host = "https://fake.invalid"
    prompt_caching = "explicit"  # an OpenAI-shaped body carries no markers: nothing is cached

    def __init__(self) -> None:
        self.image_sizes: list[tuple[int, int]] = []

    def image_tokens(self, width: int, height: int) -> int:
        self.image_sizes.append((width, height))
        return 1234

    def check_options(self, options: GenerationOptions) -> None:
        if options.temperature is not None:
            raise ConfigError("generation.temperature", "the fake API takes none")


def test_a_fake_api_registered_once_shows_up_everywhere(monkeypatch):
    fake = FakeApi()
    monkeypatch.setitem(ADAPTERS, fake.name, fake)
    assert get_adapter(fake.name) is fake

    # Config: the default host, and the option check an endpoint of the API runs.
    assert ModelEndpoint.model_construct(name="f", api=fake.name).resolved_base_url == (
        "https://fake.invalid/v1"
    )

    # The dry-run's estimate prices images by the registered rule (unwrapped: uncached).
    a = Assumptions()
    usage = episode_usage.__wrapped__("grasp_single_cube", "active", 2, (64, 48), fake.name, a)
    assert (64, 48) in fake.image_sizes and usage.input_tokens > 1234
    fake.image_sizes.clear()

    system = "You control a robot arm. " * 300  # long enough to be cached, if the API caches
    request = ChatRequest(
        system=system, turns=(Turn.user("Step 1/50.", synthetic_image(320, 240, seed=1)),)
    )

    hot = GenerationOptions(temperature=0.5)

    async def main():
        config = ServerConfig(policy="scripted", policy_options={"replies": ["ok"] * 8})
        async with LocalServer(config) as server:
            endpoints = [
                ModelEndpoint.model_construct(
                    name="f", api=fake.name, base_url=server.base_url(fake.name)
                ),
                ModelEndpoint(name="o", api="openai_chat", base_url=server.base_url("openai_chat")),
            ]
            async with LLMPool(endpoints) as pool:
                fake_calls = [await pool.complete("f", request) for _ in range(2)]
                openai_calls = [await pool.complete("o", request) for _ in range(2)]
                with pytest.raises(ConfigError, match="fake API takes none"):
                    await pool.complete("f", ChatRequest(request.turns, system, hot))
            return fake_calls, openai_calls, list(server.log)

    fake_calls, openai_calls, log = asyncio.run(main())
    # The server served the fake route and the pool parsed its answers.
    assert [r.api for r in log] == [fake.name] * 2 + ["openai_chat"] * 2
    assert all(r.status == 200 for r in log) and fake_calls[0].text == "ok"
    # Client (TPM estimate) and server (usage) priced the image by the fake's rule.
    assert fake.image_sizes == [(320, 240)] * 4
    extra = fake_calls[0].usage.prompt_tokens - openai_calls[0].usage.prompt_tokens
    assert extra == 1234 - openai_image_tokens(320, 240)
    # The server simulated the fake's prompt caching, not OpenAI's (which reads the repeat).
    assert fake_calls[1].usage.cached_input_tokens == 0
    assert openai_calls[1].usage.cached_input_tokens > 0


# -- nothing restates the registry ------------------------------------------------------------

API_NAMES = frozenset(ADAPTERS)


def _names_in(node: ast.AST) -> list[str]:
    return [
        n.value
        for n in ast.walk(node)
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value in API_NAMES
    ]


def restated_api_names(path: Path) -> list[str]:
    """Where `path` names the APIs by hand: a comparison or match with an API's name (a
    per-API decision), or a literal collection holding two or more names (a per-API mapping,
    a list of the APIs, a `Literal[...]` of them). One name passed as an argument is a choice
    of API, not a restatement (`server.endpoint_config("m", "openai_chat")`)."""
    problems = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Compare | ast.MatchValue) and _names_in(node):
            problems.append((node.lineno, f"decides by API name {_names_in(node)}"))
        elif isinstance(node, ast.Dict | ast.Tuple | ast.List | ast.Set):
            direct = [*getattr(node, "keys", []), *getattr(node, "values", [])]
            direct += getattr(node, "elts", [])
            names = [
                e.value
                for e in direct
                if isinstance(e, ast.Constant) and isinstance(e.value, str) and e.value in API_NAMES
            ]
            if len(names) >= 2:
                problems.append((node.lineno, f"lists the APIs by hand {names}"))
    return [f"{path}:{line}: {what}" for line, what in sorted(problems)]


def test_no_module_names_the_apis_by_hand():
    """The registry's own modules aside, vabench and the benchmarks derive every per-API
    choice from `apis.ADAPTERS`."""
    ours = [p for p in sorted(ROOT.rglob("*.py")) if REGISTRY_DIR not in p.parents]
    # goldens.py records each API's exact wire body from a hand-written case per API, as the
    # tests do: its per-API cases are the point, not a restated registry.
    paths = ours + [p for p in sorted(BENCHMARKS.glob("*.py")) if p.name != "goldens.py"]
    problems = [line for path in paths for line in restated_api_names(path)]
    assert not problems, "derive these from apis.ADAPTERS:\n" + "\n".join(problems)


def test_the_scan_sees_a_restated_mapping_and_a_decision_by_name(tmp_path):
    """The scan above can fail: a hand-written image-rule table and a branch on a name."""
    module = tmp_path / "m.py"
    module.write_text(
        "from typing import Literal\n"
        "RULES = {'openai_chat': 1, 'anthropic': 2}\n"
        "Api = Literal['openai_chat', 'openai_responses']\n"
        "def f(api):\n"
        "    return 1 if api == 'anthropic' else 2\n"
        "CHOSEN = g('anthropic')\n"
    )
    assert [p.split(": ")[1] for p in restated_api_names(module)] == [
        "lists the APIs by hand ['openai_chat', 'anthropic']",
        "lists the APIs by hand ['openai_chat', 'openai_responses']",
        "decides by API name ['anthropic']",
    ]
