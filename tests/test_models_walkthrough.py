"""The example model entries work as written: every entry of
configs/models.example.yaml (OpenAI, Anthropic, a local vLLM and Ollama through their
OpenAI-compatible endpoints), copied verbatim into a sweep config with only its `base_url`
pointed at a real server on loopback (the embedded server's code, run as an outside endpoint,
keyed where the entry names a key), runs an episode through the command: every field the
examples use is accepted, each API's wire format is the one the server parses, keys come from
the variables the entries name."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.llm_pool.testing import server_in_thread
from vabench.run_layout import RESULTS
from vabench.sweep.__main__ import main

ROOT = Path(__file__).resolve().parents[1]
KEY = "walkthrough-key"


def _outside(api_key: str | None) -> Iterator[LocalServer]:
    """A real endpoint the sweep does not start (requiring `api_key` when given)."""
    with server_in_thread(ServerConfig(policy="conversation_hash", api_key=api_key)) as server:
        yield server


@pytest.fixture(scope="module")
def keyed() -> Iterator[LocalServer]:
    yield from _outside(KEY)


@pytest.fixture(scope="module")
def open_server() -> Iterator[LocalServer]:
    """Like a local vLLM or Ollama started without authentication."""
    yield from _outside(None)


EXAMPLES = yaml.safe_load((ROOT / "configs" / "models.example.yaml").read_text())["models"]


@pytest.mark.parametrize("entry", EXAMPLES, ids=[m["name"] for m in EXAMPLES])
def test_an_example_entry_runs_as_written(entry, keyed, open_server, tmp_path, monkeypatch):
    provider = keyed if "api_key_env" in entry else open_server
    model = {**entry, "base_url": provider.base_url(entry["api"])}
    if "api_key_env" in entry:
        monkeypatch.setenv(entry["api_key_env"], KEY)
    config = {
        "name": "walkthrough",
        "models": [model],
        "tracks": ["active"],
        "tasks": ["grasp_single_cube"],
        "seeds": {"verified": 1},
        "runs": 1,
        "step_budget": 2,
        "simulator": {"backend": "c"},
        "render": {"width": 64, "height": 48, "workers": 1},
        "summaries": "none",
    }
    path = tmp_path / "sweep.yaml"
    path.write_text(yaml.safe_dump(config))
    out = tmp_path / "out"
    assert main([str(path), "--out", str(out), "--plain", "--no-report"]) == 0
    records = [json.loads(x) for x in (out / RESULTS).read_text().splitlines()]
    assert len(records) == 1 and records[0]["model"] == entry["name"]
    assert records[0]["status"] in ("success", "failure")
    assert records[0]["model_calls"] >= 1
