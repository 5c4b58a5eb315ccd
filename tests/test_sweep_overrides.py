"""The sweep's quick-trial flags (`vabench.config.overrides`), each through the command: they
edit the config before it is checked, the dry run lists them with the resulting plan, a real
run records exactly the overridden plan (and refuses a resume under other overrides), a bad
name or value is one line naming it and the flag, and `--model NAME --model-base-url URL`
evaluates a real OpenAI-compatible endpoint on loopback that the config does not name."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from vabench.llm_pool.server import ServerConfig
from vabench.llm_pool.testing import server_in_thread
from vabench.run_layout import RESULTS
from vabench.sweep.__main__ import main

# 2 models x 2 tracks x 2 tasks x 2 seeds x 2 runs = 32 episodes as written
CONFIG = """\
name: overrides
models:
  - {name: local, api: openai_chat, base_url: embedded}
  - {name: other, api: openai_chat, base_url: embedded, limits: {min_concurrency: 4}}
embedded_server: {policy: conversation_hash}
tracks: [active, passive]
tasks: [grasp_single_cube, lift_pot]
seeds: {verified: 2}
runs: 2
step_budget: 2
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
"""
TINY = ["--tasks", "grasp_single_cube", "--tracks", "active", "--seeds", "1", "--runs", "1"]


@pytest.fixture
def config(tmp_path: Path) -> Path:
    path = tmp_path / "overrides.yaml"
    path.write_text(CONFIG)
    return path


def ledger(run_dir: Path) -> list[dict]:
    path = run_dir / RESULTS
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def planned(out: str) -> int:
    return int(next(x for x in out.splitlines() if x.startswith("Planned episodes:")).split()[-1])


def test_dry_run_lists_the_overrides_and_the_plan_they_give(config, tmp_path, capsys):
    out = str(tmp_path / "out")
    assert main([str(config), "--dry-run", "--out", out]) == 0
    shown = capsys.readouterr().out
    assert planned(shown) == 32 and "overrides:" not in shown

    assert main([str(config), "--dry-run", "--out", out, *TINY]) == 0
    shown = capsys.readouterr().out
    assert "overrides: --tasks grasp_single_cube, --tracks active, --seeds 1, --runs 1" in shown
    assert planned(shown) == 2  # both models

    assert main([str(config), "--dry-run", "--out", out, *TINY, "--model", "other"]) == 0
    assert planned(capsys.readouterr().out) == 1

    # --limit keeps the first N of the plan's order (task > model > track > run > seed)
    assert main([str(config), "--dry-run", "--out", out, "--limit", "5"]) == 0
    shown = capsys.readouterr().out
    assert "overrides: --limit 5" in shown and planned(shown) == 5
    assert "lift_pot" not in shown.split("Estimate")[0]  # the first task's episodes only


@pytest.mark.parametrize(
    "flags, expected",
    [
        (["--model", "gpt"], "error: --model gpt: no model 'gpt' in the config; its models: "),
        (["--tasks", "grasp_single_cub"], "tasks[0]: unknown task 'grasp_single_cub'; did you"),
        (["--tracks", "activ"], "tracks[0]: "),
        (["--runs", "0"], "runs: must be at least 1, got 0 (from --runs"),
        (["--seeds", "x"], "seeds.verified: expected a whole number >= 1, got 'x' (from --seeds"),
        (["--max-episodes", "0"], "executor.max_episodes: must be at least 1"),
        (["--max-connections", "2"], "models[1].limits: "),  # below other's min_concurrency 4
        (["--limit", "0"], "error: --limit: expected a whole number >= 1, got '0'"),
        (["--model-base-url", "http://127.0.0.1:9/v1"], "--model-base-url needs --model NAME"),
    ],
)
def test_a_bad_name_or_value_is_one_line_naming_it(config, tmp_path, capsys, flags, expected):
    out = tmp_path / "out"
    assert main([str(config), "--dry-run", "--out", str(out), *flags]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0], captured.err
    if flags[0] == "--model":
        assert "local, other" in lines[0]
    if flags[0] in ("--tracks", "--max-connections"):
        assert f"(from {flags[0]} {flags[1]})" in lines[0]
    assert not out.exists()


def test_a_run_records_exactly_the_overridden_plan_and_holds_to_it(config, tmp_path, capsys):
    out = tmp_path / "out"
    flags = [str(config), "--out", str(out), "--plain", "--no-report", *TINY, "--model", "local"]
    assert main(flags) == 0
    records = ledger(out)
    assert [(r["model"], r["track"], r["task"], r["run"]) for r in records] == [
        ("local", "active", "grasp_single_cube", 1)
    ]
    assert len(json.loads((out / "plan.json").read_text())["episodes"]) == 1
    before = (out / RESULTS).read_bytes()
    capsys.readouterr()

    # the same overrides resume (nothing left to run); others are refused like a changed config
    assert main(flags) == 0
    assert (out / RESULTS).read_bytes() == before
    capsys.readouterr()
    plain = flags[: flags.index("--tasks")]
    for args, field in (
        ([*flags, "--runs", "2"], "runs: 1 -> 2"),
        ([*flags, "--model", "other"], "models[other]"),  # both models now
        ([*flags, "--limit", "1"], None),  # the same one episode: the plan holds
        (plain, "tasks:"),  # no overrides: the config's own plan
    ):
        code = main(args)
        err = capsys.readouterr().err
        if field is None:
            assert code == 0, err
        else:
            assert code == 2 and field in err and "different plan" in err, err
        assert (out / RESULTS).read_bytes() == before


@pytest.fixture
def outside_server() -> Iterator[str]:
    """A real OpenAI-compatible endpoint the config does not name, wanting a key (its URL)."""
    config = ServerConfig(policy="conversation_hash", api_key="trial-key")
    with server_in_thread(config) as server:
        yield server.base_url("openai_chat")


def test_model_base_url_evaluates_an_endpoint_the_config_does_not_name(
    config, tmp_path, capsys, outside_server, monkeypatch
):
    monkeypatch.setenv("TRIAL_KEY", "trial-key")
    out = tmp_path / "out"
    endpoint = ["--model", "org/served", "--model-base-url", outside_server]
    args = [str(config), "--out", str(out), "--plain", "--no-report", *TINY, *endpoint]

    assert main([*args, "--dry-run"]) == 0
    shown = capsys.readouterr().out
    assert f"--model org/served, --model-base-url {outside_server}" in shown
    assert planned(shown) == 1

    # without its key the endpoint refuses: the sweep stops naming the model, records nothing
    assert main(args) == 2
    assert "served" in capsys.readouterr().err and ledger(out) == []

    assert main([*args, "--model-key-env", "TRIAL_KEY"]) == 0
    records = ledger(out)
    assert [(r["model"], r["status"] in ("success", "failure")) for r in records] == [
        ("served", True)
    ]
    written = (out / "sweep.yaml").read_text()
    assert "model: org/served" in written and outside_server in written
