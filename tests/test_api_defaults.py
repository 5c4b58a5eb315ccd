"""The benchmark's API defaults on the wire (docs/PROTOCOL.md, "API defaults"): sent where a
model's config leaves the field unset, the user's value where it names one, nothing where it
says `off`; a report names every model whose config changed a default."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from vabench.agent.generation import request_options
from vabench.llm_pool import ModelEndpoint
from vabench.llm_pool.apis import ADAPTERS
from vabench.llm_pool.apis.base import encode_body
from vabench.llm_pool.messages import ChatRequest, Turn
from vabench.report.results_file import api_setting_notes


def wire_body(api: str, generation: dict[str, Any]) -> dict[str, Any]:
    """The body the pool sends for one request under `generation` (its own merge order: the
    endpoint's options, then the request's, which carry the protocol's defaults)."""
    endpoint = ModelEndpoint(name="m", api=api, model="m", generation=generation)
    request = ChatRequest((Turn.user("observation 1"),), "system", request_options(endpoint, None))
    options = endpoint.generation.merge(request.options)
    body = ADAPTERS[api].build_body(endpoint, request, options)
    return json.loads(encode_body(body))  # type: ignore[no-any-return]


def reasoning(api: str, body: dict[str, Any]) -> Any:
    if api == "openai_chat":
        return body.get("reasoning_effort")
    if api == "openai_responses":
        return (body.get("reasoning") or {}).get("effort")
    thinking = body.get("thinking")
    return None if thinking is None else thinking["budget_tokens"]


@pytest.mark.parametrize(
    ("api", "option", "default", "own"),
    [
        ("openai_chat", "reasoning_effort", "medium", "high"),
        ("openai_responses", "reasoning_effort", "medium", "low"),
        ("anthropic", "thinking_budget", 1024, 2048),
    ],
)
def test_a_default_is_sent_a_users_value_wins_and_off_sends_nothing(api, option, default, own):
    assert reasoning(api, wire_body(api, {})) == default
    assert reasoning(api, wire_body(api, {option: own})) == own
    body = wire_body(api, {option: "off"})
    assert reasoning(api, body) is None
    assert not {"reasoning_effort", "reasoning", "thinking"} & set(body)


def test_off_is_no_option_of_the_other_api_and_bad_values_name_their_field():
    # `off` names no option, so it may stand in any model's config
    wire_body("openai_chat", {"thinking_budget": "off"})
    wire_body("anthropic", {"reasoning_effort": "off"})
    with pytest.raises(ValueError, match=r"generation\.reasoning_effort: OpenAI only"):
        ModelEndpoint(name="m", api="anthropic", model="m", generation={"reasoning_effort": "low"})
    with pytest.raises(ValueError, match="thinking_budget"):
        ModelEndpoint(name="m", api="anthropic", model="m", generation={"thinking_budget": 512})
    with pytest.raises(ValueError, match="reasoning_effort"):
        ModelEndpoint(name="m", api="openai_chat", model="m", generation={"reasoning_effort": "no"})


def test_the_report_names_each_changed_default(tmp_path: Path):
    models = [
        {"name": "plain", "api": "openai_chat", "generation": {}},
        {"name": "as-paper", "api": "openai_chat", "generation": {"reasoning_effort": "medium"}},
        {"name": "no-reasoning", "api": "openai_chat", "generation": {"reasoning_effort": "off"}},
        {"name": "deep", "api": "anthropic", "generation": {"thinking_budget": 4096}},
    ]
    (tmp_path / "plan.json").write_text(json.dumps({"fields": {"models": models}}))
    notes = api_setting_notes(tmp_path)
    assert len(notes) == 2
    assert notes[0].startswith("no-reasoning: generation.reasoning_effort off (not sent;")
    assert "default is medium" in notes[0]
    assert notes[1].startswith("deep: generation.thinking_budget 4096 (4096 sent;")
    assert api_setting_notes(tmp_path / "missing") == []
