"""`python -m vabench.check` against the embedded server answering as real local servers do:
vLLM with a 1-image limit, vLLM with a 32k context, a server that cuts prompts without a word
(Ollama's num_ctx), llama.cpp's server that does not read max_completion_tokens, and one with
none of these limits. Real loopback HTTP, the real command in a subprocess; and the sweep's
first step, which stops before any episode is recorded."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest

from vabench.check import judge
from vabench.check.inputs import probe
from vabench.config import load_config
from vabench.llm_pool.config import ModelEndpoint
from vabench.llm_pool.server_config import ServerConfig, ServerTraits
from vabench.llm_pool.testing import server_in_thread
from vabench.run_layout import RunDir

ROOT = Path(__file__).resolve().parents[1]
LONG_REPLY = " ".join(["one, two, three, four, five, six, seven, eight"] * 8)

SERVERS = {
    "one-image": ServerTraits(served_model_name="qwen-vl", max_images_per_prompt=1),
    "short-context": ServerTraits(served_model_name="qwen-vl", max_model_len=32768),
    "truncating": ServerTraits(num_ctx=2048),
    "llama-cpp": ServerTraits(ignored_fields=["max_completion_tokens"]),
    "reasoning-max-tokens": ServerTraits(reasoning_model=True),
    "reasoning-temperature": ServerTraits(reasoning_model=True),
    "no-reasoning": ServerTraits(no_reasoning=True),
    "healthy": ServerTraits(served_model_name="qwen-vl", max_model_len=300_000),
    "no-reasoning-off": ServerTraits(no_reasoning=True, max_model_len=300_000),
}
"""Model name -> the limits of the server behind it."""
FIELDS = {
    "reasoning-max-tokens": ", max_tokens_field: max_tokens",
    "reasoning-temperature": ", generation: {temperature: 0.2}",
    "no-reasoning-off": ", generation: {reasoning_effort: off}",  # YAML's false: read as off
}
"""Model name -> what its config entry sets besides its name and address."""

CONFIG = """\
name: check
models:
{models}
  - {{name: embedded, api: openai_chat, base_url: embedded}}
tracks: [active, passive]
tasks: [grasp_single_cube]
seeds: [1000]
runs: 1
step_budget: 3
render: {{width: 320, height: 240}}
"""


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Iterator[Path]:
    """A sweep config with one model per server of `SERVERS`, each server running."""
    with ExitStack() as stack:
        entries = []
        replies = {"replies": [LONG_REPLY], "cycle": True}
        for name, traits in SERVERS.items():
            served = ServerConfig(imitate=traits, policy="scripted", policy_options=replies)
            url = stack.enter_context(server_in_thread(served)).base_url("openai_chat")
            entry = f"{{name: {name}, api: openai_chat, model: qwen-vl, base_url: '{url}'"
            entry += FIELDS.get(name, "") + "}"
            entries.append(f"  - {entry}")
        path = tmp_path_factory.mktemp("check") / "check.yaml"
        path.write_text(CONFIG.format(models="\n".join(entries)))
        yield path


SOUND = ["healthy", "no-reasoning-off"]
FAULTY = [name for name in SERVERS if name not in SOUND]


@pytest.fixture(scope="module")
def checked(config) -> dict[str, subprocess.CompletedProcess[str]]:
    """`python -m vabench.check CONFIG --model ...`: the faulty models in one run, the sound
    ones in another, side by side (a command's start takes seconds on a small machine)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "XDG_CACHE_HOME": str(config.parent / "cache")}
    groups = {"faulty": FAULTY, "sound": [*SOUND, "embedded"]}
    runs = {
        group: subprocess.Popen(
            [sys.executable, "-m", "vabench.check", str(config)]
            + [arg for name in names for arg in ("--model", name)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            cwd=config.parent,
        )
        for group, names in groups.items()
    }
    done = {}
    for group, proc in runs.items():
        out, err = proc.communicate(timeout=300)
        done[group] = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    return done


def problem_lines(run: subprocess.CompletedProcess[str], model: str) -> list[str]:
    """The problem lines of `model` (all of them begin with its name)."""
    return [line for line in run.stderr.splitlines() if line.startswith(f"model {model!r}: ")]


def test_every_faulty_model_has_one_problem_line(checked):
    run = checked["faulty"]
    assert run.returncode == 2, run.stderr
    assert [len(problem_lines(run, m)) for m in FAULTY] == [1] * len(FAULTY), run.stderr
    assert f"{len(FAULTY)} problem(s)" in run.stderr


def test_a_vllm_image_limit_is_named_with_the_flag_that_lifts_it(checked):
    run = checked["faulty"]
    assert run.returncode == 2, run.stderr
    (line,) = problem_lines(run, "one-image")
    assert line.startswith("model 'one-image': images: ")
    assert "At most 1 image(s) may be provided in one request." in line
    assert "--limit-mm-per-prompt '{\"image\": 16}'" in line  # the learning stage's 8 + 8


def test_a_32k_context_is_held_against_the_plans_need(checked):
    run = checked["faulty"]
    assert run.returncode == 2, run.stderr
    (line,) = problem_lines(run, "short-context")
    assert line.startswith("model 'short-context': context: the server holds 32,768 tokens")
    assert "max_model_len" in line and "models[1].context_window: 32768" in line


def test_a_server_that_cuts_the_prompt_is_caught_by_its_count(checked):
    run = checked["faulty"]
    assert run.returncode == 2, run.stderr
    (line,) = problem_lines(run, "truncating")
    assert line.startswith("model 'truncating': prompt tokens: 2,048 counted")
    assert "num_ctx" in line and "OLLAMA_CONTEXT_LENGTH" in line


def test_an_unread_output_limit_field_is_named(checked):
    run = checked["faulty"]
    assert run.returncode == 2, run.stderr
    (line,) = problem_lines(run, "llama-cpp")
    assert line.startswith("model 'llama-cpp': output limit: ")
    assert "models[3].max_tokens_field: max_tokens" in line


def test_a_reasoning_models_refused_parameters_are_named(checked):
    run = checked["faulty"]
    assert run.returncode == 2, run.stderr
    (line,) = problem_lines(run, "reasoning-max-tokens")
    assert line.startswith("model 'reasoning-max-tokens': output limit: the server refuses max")
    assert "models[4].max_tokens_field: max_completion_tokens" in line
    (line,) = problem_lines(run, "reasoning-temperature")
    assert "'temperature' does not support 0.2" in line
    assert "remove models[5].generation.temperature" in line


def test_a_refused_reasoning_option_is_named_with_the_value_that_switches_it_off(checked):
    run = checked["faulty"]
    assert run.returncode == 2, run.stderr
    (line,) = problem_lines(run, "no-reasoning")
    assert line.startswith("model 'no-reasoning': reasoning: the server refuses the benchmark's")
    assert "'reasoning_effort' is not supported with this model" in line
    assert "set models[6].generation.reasoning_effort: off" in line
    # with the option switched off the same server passes (the sound run below)
    assert "check: model 'no-reasoning-off'" in checked["sound"].stdout


def test_a_server_without_those_limits_passes_every_item(checked):
    run = checked["sound"]
    assert run.returncode == 0, run.stderr
    rows = run.stdout.splitlines()
    assert rows[0] == "check: model 'healthy'"
    items = len(judge.ITEMS)
    assert [row.split()[0] for row in rows[1 : 1 + items]] == [i.split()[0] for i in judge.ITEMS]
    assert "PROBLEM" not in run.stdout
    assert "300,000 tokens (max_model_len) hold the" in run.stdout


def test_a_checked_models_latency_times_the_dry_run(checked, config, capsys, monkeypatch):
    """The check keeps each sound API model's latency on this machine; a dry run of a model
    no sweep has measured here gives the longest wall time at it, within its limits."""
    from vabench.check import latency
    from vabench.check.latency import api_kind, measured
    from vabench.sweep.__main__ import main

    written = config.parent / "cache" / "vabench" / "check_latency.json"  # the subprocesses'
    times = measured(written)
    cfg = load_config(config, require_keys=False)
    assert set(times) == {api_kind(cfg, "healthy")}  # every model here is one kind
    assert 0 < times[api_kind(cfg, "healthy")].latency_s < 60
    monkeypatch.setattr(latency, "latency_file", lambda: written)
    out = config.parent / "dry"
    assert main([str(config), "--out", str(out), "--model", "healthy", "--dry-run"]) == 0
    printed = capsys.readouterr().out
    line = next(x for x in printed.splitlines() if x.startswith("wall time (openai_chat"))
    assert "at the endpoint check's" in line and "decisions a second" in line
    assert "no expected time" in line
    # on a machine whose check never timed it, the dry run says that nothing is measured
    monkeypatch.setattr(latency, "latency_file", lambda: config.parent / "none" / "x.json")
    assert main([str(config), "--out", str(out), "--model", "healthy", "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert "at the endpoint check's" not in printed and "no measured pace" in printed


def test_the_embedded_server_needs_no_call(checked):
    run = checked["sound"]
    assert run.returncode == 0, run.stderr
    assert "check: model 'embedded'\n  reachable     the embedded server: nothing" in run.stdout


@pytest.mark.endpoint_check
def test_the_sweep_checks_first_and_records_nothing_on_a_problem(config, tmp_path, capsys):
    from vabench.sweep.__main__ import main

    out = tmp_path / "out"
    args = [str(config), "--out", str(out), "--plain", "--no-report", "--model", "one-image"]
    assert main([*args, "--dry-run"]) == 0
    assert "check:     first, one decision for each of 1 model(s)" in capsys.readouterr().out
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "error: model 'one-image': images: " in err and "--limit-mm-per-prompt" in err
    assert not RunDir(out).results.exists()


def test_the_probe_is_the_heaviest_request_of_the_plan(config):
    cfg = load_config(config, require_keys=False)
    heavy = probe(cfg, "healthy")
    assert heavy.images == 16 and "learning request" in heavy.images_why
    assert all(len(i.data) > 1000 for i in heavy.request.images)  # real JPEGs, not headers
    assert heavy.least_tokens < heavy.estimate("openai_chat")
    unlearned = cfg.tracks[1].model_copy(update={"summaries": "none"})
    passive_only = probe(cfg.model_copy(update={"tracks": (unlearned,)}), "healthy")
    assert passive_only.images == 5 and "passive five-view bundle" in passive_only.images_why


@pytest.mark.parametrize(
    ("status", "message", "item", "fix"),
    [
        (
            400,
            "Unsupported parameter: 'max_tokens' is not supported with this model. Use "
            "'max_completion_tokens' instead.",
            "output limit",
            "max_tokens_field: max_completion_tokens",
        ),
        (
            400,
            "Unsupported value: 'temperature' does not support 0.2 with this model. Only the "
            "default (1) value is supported.",
            "output limit",
            "generation.temperature",
        ),
        (400, "No connected db.", "key", "check the key in OPENAI_API_KEY"),
        (401, "Incorrect API key provided: sk-...", "key", "check the key in OPENAI_API_KEY"),
        (
            400,
            "Invalid 'max_tokens': integer below minimum value.",
            "reachable",
            "max_tokens_field",
        ),
        (404, "The model `qwen-vl` does not exist.", "model name", "models[0].model"),
        (
            400,
            "This model's maximum context length is 32768 tokens. However, you requested 40000 "
            "tokens (35904 in the messages, 4096 in the completion).",
            "context",
            "--max-model-len",
        ),
    ],
)
def test_refusals_are_read_by_what_they_say(status, message, item, fix):
    endpoint = ModelEndpoint(name="m", api="openai_chat", api_key_env="OPENAI_API_KEY")
    body = f'HTTP {status}: {{"error": {{"message": "{message}", "type": "x"}}}}'
    line = judge.rejection(judge.Where(endpoint, 0), status, body, 5, "the passive bundle")
    assert (line.item, line.problem) == (item, True) and fix in (line.fix or "")
    assert message[:40] in line.text


def test_a_refusal_that_is_no_json_error_names_its_status_once():
    """A gateway's plain-text answer (the failure line is `HTTP 400: <its words>`): the
    problem line quotes the words, its status named once."""
    endpoint = ModelEndpoint(name="m", api="openai_chat", api_key_env="OPENAI_API_KEY")
    line = judge.rejection(judge.Where(endpoint, 0), 400, "HTTP 400: No connected db.", 5, "")
    assert 'HTTP 400 "No connected db."' in line.text and line.text.count("HTTP 400") == 1
    assert line.item == "key" and "OPENAI_API_KEY" in (line.fix or "")


def test_the_server_command_takes_each_limit():
    from vabench.llm_pool.serve import build_parser, config_from_args

    flags = ["--served-model-name", "qwen-vl", "--max-model-len", "32768", "--limit-images", "1"]
    flags += ["--num-ctx", "2048", "--ignore-field", "max_completion_tokens", "--reasoning-model"]
    traits = config_from_args(build_parser().parse_args(flags)).imitate
    assert traits == ServerTraits(
        served_model_name="qwen-vl",
        max_model_len=32768,
        max_images_per_prompt=1,
        num_ctx=2048,
        ignored_fields=["max_completion_tokens"],
        reasoning_model=True,
    )
    assert config_from_args(build_parser().parse_args([])).imitate == ServerTraits()


PASSIVE_ONLY = """\
name: check
models:
  - {{name: small, api: openai_chat, model: qwen-vl, base_url: '{small}'}}
  - {{name: roomy, api: openai_chat, model: qwen-vl, base_url: '{roomy}'}}
tracks: [{{name: passive, protocol: passive, summaries: none}}]
tasks: [grasp_single_cube]
seeds: [1000]
runs: 1
step_budget: 3
render: {{width: 320, height: 240}}
"""


def test_a_context_cut_above_the_first_steps_floor_is_caught_by_the_long_probe(tmp_path):
    """A passive-only sweep on a server that cuts prompts at 4,096 tokens without an error
    (Ollama's num_ctx) and reports no context: the first step's count (4,096) is above the
    fewest tokens an honest server could count for it, so it passes; the long text probe is
    counted at 4,096 and named, with the context to start the server with. A server that cuts
    nothing passes."""
    import asyncio

    from vabench.check.run import check_config

    replies = {"replies": ["ok"], "cycle": True}
    small = ServerConfig(
        imitate=ServerTraits(num_ctx=4096), policy="scripted", policy_options=replies
    )
    roomy = ServerConfig(policy="scripted", policy_options=replies)
    with server_in_thread(small) as s, server_in_thread(roomy) as r:
        path = tmp_path / "check.yaml"
        text = PASSIVE_ONLY.format(small=s.base_url("openai_chat"), roomy=r.base_url("openai_chat"))
        path.write_text(text)
        config = load_config(path, require_keys=False)
        first = probe(config, "small")
        # the first step's honest floor is below the cut: its count alone cannot tell
        assert first.least_tokens < 4096
        reports = asyncio.run(check_config(config, {}))
    prompt = next(line for line in reports["small"] if line.item == "prompt tokens")
    assert not prompt.problem, prompt
    (context,) = [line for line in reports["small"] if line.item == "context"]
    assert context.problem and "counted as 4,096" in context.text, context
    assert "OLLAMA_CONTEXT_LENGTH=" in (context.fix or "")
    problems = [line for line in reports["roomy"] if line.problem]
    assert not problems, problems
    (whole,) = [line for line in reports["roomy"] if line.item == "context"]
    assert "was counted whole" in whole.text, whole


def test_the_check_latency_bound_keeps_to_the_models_rpm_and_concurrency(config):
    from vabench.check.latency import CheckLatency
    from vabench.check.pace import latency_line

    cfg = load_config(config, require_keys=False)
    check = CheckLatency(latency_s=2.0, checked_at=0.0)
    limits = cfg.model("healthy").limits  # max_concurrency 64: 32 decisions a second at 2 s
    assert limits.max_concurrency == 64 and limits.rpm is None
    line = latency_line(cfg, "k", ["healthy"], [100] * 192, check)  # 19,200 decisions
    assert "at most 10 min" in line and "32 decisions a second" in line and "concurrency" in line
    capped = cfg.model_copy(
        update={
            "models": tuple(
                m.model_copy(update={"limits": m.limits.model_copy(update={"rpm": 600})})
                for m in cfg.models
            )
        }
    )
    line = latency_line(capped, "k", ["healthy"], [100] * 192, check)  # 10 a second: 32 min
    assert "at most 32 min" in line and "(the models' limits: rpm)" in line
