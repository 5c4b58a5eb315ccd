"""Episode records and how errors end an episode: events.jsonl, frames/ and result.json agree
with each other; an outlasted provider gives an unscored infrastructure error with its
result written; a finished directory is never overwritten and an interrupted one is set
aside; and `python -m vabench.episode` writes the same records from the command line."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from engine_util import SMALL, STOP, EpisodeRun, camera, move, run_scripted, tool
from PIL import Image

from vabench.agent.conversation import ContextLimits
from vabench.agent.observation import PASSIVE_VIEWS
from vabench.agent.records import RECORD_VERSION, read_events, read_result
from vabench.agent.services import EngineSettings
from vabench.llm_pool.server import ServerConfig
from vabench.render.worker import RenderPool

TASK = "grasp_single_cube"
SEED = 1000
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def pool():
    with RenderPool(workers=1, timeout_s=60) as p:
        yield p


def active_script() -> list[str]:
    return [
        camera("view_topdown"),
        tool("geometry.verify"),
        "not a decision",
        move("z", "+", 10),
        tool("camera.history", step=1),
        move("x", "-", 10),
        STOP,
    ]


def passive_script(arm: str | None) -> list[str]:
    return [move("z", "+", 10, arm=arm), "{broken", tool("geometry.verify"), STOP]


def _check_records(run: EpisodeRun, directory: Path) -> None:
    events = read_events(directory)
    raw_lines = (directory / "events.jsonl").read_text(encoding="utf-8").splitlines()
    assert len(raw_lines) == len(events)  # every line parsed
    assert all(e["v"] == RECORD_VERSION for e in events)
    assert [e["seq"] for e in events] == list(range(len(events)))
    assert events == run.events  # the file is what the engine recorded, nothing lost
    assert events[0]["type"] == "episode_start" and events[-1]["type"] == "end"

    # every observation's frames exist and are images of the configured size
    observations = [e for e in events if e["type"] == "observation"]
    assert observations
    for e in observations:
        for rel in e["frames"]:
            with Image.open(io.BytesIO((directory / rel).read_bytes())) as img:
                assert img.format == "JPEG" and img.size == (SMALL.width, SMALL.height), rel
    frames_on_disk = sorted(p.name for p in (directory / "frames").iterdir())
    assert frames_on_disk == sorted(Path(rel).name for e in observations for rel in e["frames"])

    # result.json agrees with the events
    result = read_result(directory)
    assert result == run.result
    by_type = {t: [e for e in events if e["type"] == t] for t in {e["type"] for e in events}}
    assert result.steps_used == result.robot_actions + result.camera_actions
    assert result.robot_actions == len(by_type.get("action", []))
    assert result.camera_actions == len(by_type.get("camera", []))
    assert result.tool_calls == len(by_type.get("tool", []))
    assert result.invalid_outputs == len(by_type.get("rejection", []))
    replies = by_type["reply"]
    assert len(replies) == len(by_type["request"])
    # every call is logged with its usage: the decisions' replies and the compactions' summaries
    calls = replies + by_type.get("compaction", [])
    assert result.model_calls == len(calls)
    usage = {k: sum(e["usage"][k] or 0 for e in calls) for k in replies[0]["usage"]}
    assert result.cost_usd == pytest.approx(sum(e["cost_usd"] for e in calls))
    assert usage["input_tokens"] > 0 and usage["output_tokens"] > 0
    assert result.tokens.input == usage["input_tokens"]
    assert result.tokens.cached_input == usage["cached_input_tokens"]
    assert result.tokens.cache_write == usage["cache_write_tokens"]
    assert result.tokens.output == usage["output_tokens"]
    assert result.tokens.reasoning == usage["reasoning_tokens"]
    end = events[-1]
    assert (end["status"], end["stop_reason"]) == (result.status, result.stop_reason)


def test_active_records_agree(pool, tmp_path):
    run = run_scripted(TASK, active_script(), pool, seed=SEED, budget=6, out_dir=tmp_path)
    r = run.result
    assert (r.status, r.stop_reason) == ("failure", "model_stop"), r.error
    assert (r.robot_actions, r.camera_actions, r.tool_calls, r.invalid_outputs) == (2, 1, 2, 1)
    _check_records(run, tmp_path)
    names = sorted(p.name for p in (tmp_path / "frames").iterdir())
    assert names == [f"step_{i:03d}.jpg" for i in range(1, 5)]


@pytest.mark.parametrize(
    ("task", "arm"), [(TASK, None), ("handover_horizontal_block", "left")], ids=["single", "dual"]
)
def test_passive_records_agree(pool, tmp_path, task, arm):
    """Five frames per observation, named by the plain view in the fixed order (dual-arm too:
    there the camera names its poses "both_<view>")."""
    run = run_scripted(
        task, passive_script(arm), pool, protocol="passive", budget=4, out_dir=tmp_path
    )
    r = run.result
    assert (r.status, r.stop_reason) == ("failure", "model_stop"), r.error
    _check_records(run, tmp_path)
    first = next(e for e in run.events if e["type"] == "observation")
    assert first["frames"] == [f"frames/step_001_{i}_{v}.jpg" for i, v in enumerate(PASSIVE_VIEWS)]


def test_an_outlasted_provider_is_an_unscored_infrastructure_error(pool, tmp_path):
    config = ServerConfig(faults={"rates": {"server_error": 1.0}})
    run = run_scripted(
        TASK,
        [STOP],
        pool,
        seed=SEED,
        out_dir=tmp_path,
        server_config=config,
        retry={"max_attempts": 2},
    )
    r = run.result
    assert (r.status, r.stop_reason, r.success, r.scored) == (
        "infrastructure_error",
        "infrastructure_error",
        False,
        False,
    )
    assert r.error is not None
    assert "after 2 attempts" in r.error and "HTTP 500" in r.error
    assert len(run.bodies) == 2  # the request and its one retry, nothing more
    assert (r.model_calls, r.steps_used) == (0, 0)
    assert read_result(tmp_path) == r
    assert read_events(tmp_path)[-1]["status"] == "infrastructure_error"


def test_a_finished_directory_is_refused(pool, tmp_path):
    run_scripted(TASK, [STOP], pool, seed=SEED, out_dir=tmp_path)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    with pytest.raises(FileExistsError, match="already holds a finished episode"):
        run_scripted(TASK, [STOP], pool, seed=SEED, out_dir=tmp_path)
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before


def test_an_interrupted_attempt_is_set_aside(pool, tmp_path):
    old_lines = '{"v": 1, "seq": 0, "type": "episode_start"}\n{"v": 1, "seq": 1, "ty'
    (tmp_path / "events.jsonl").write_text(old_lines, encoding="utf-8")
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "step_001.jpg").write_bytes(b"old frame")
    run = run_scripted(TASK, [move("z", "+", 10), STOP], pool, seed=SEED, out_dir=tmp_path)
    assert run.result.stop_reason == "model_stop"
    aside = tmp_path / "partial_1"
    assert (aside / "events.jsonl").read_text(encoding="utf-8") == old_lines
    assert (aside / "frames" / "step_001.jpg").read_bytes() == b"old frame"
    events = read_events(tmp_path)  # a clean log, not appended to the old one
    assert [e["seq"] for e in events] == list(range(len(events)))
    assert events[0]["type"] == "episode_start" and events[0]["seed"] == SEED
    assert (tmp_path / "frames" / "step_001.jpg").read_bytes() != b"old frame"
    assert read_result(tmp_path) == run.result


def test_the_command_line_writes_the_records(tmp_path):
    out = tmp_path / "episode"
    cmd = [
        *(sys.executable, "-m", "vabench.episode"),
        *("--task", TASK, "--seed", str(SEED), "--backend", "c"),
        *("--width", "160", "--height", "120", "--max-steps", "3"),
        *("--out", str(out), "--json"),
    ]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    printed = json.loads(proc.stdout)  # --json: the result document alone
    result = read_result(out)
    assert result is not None and printed == result.model_dump()
    assert (result.task, result.seed, result.step_budget) == (TASK, SEED, 3)
    assert result.scored and result.steps_used <= 3
    events = read_events(out)
    assert [e["seq"] for e in events] == list(range(len(events)))
    assert (out / "frames" / "step_001.jpg").exists()
    assert result.model_calls == sum(e["type"] == "reply" for e in events)


def test_a_rejected_request_is_an_unscored_error(pool, tmp_path):
    """A 4xx the provider will not change its mind about (here: the script has run out) ends
    the episode at once as an "error", with the step already taken recorded."""
    run = run_scripted(TASK, [camera("view_topdown")], pool, seed=SEED, out_dir=tmp_path)
    r = run.result
    assert (r.status, r.stop_reason, r.scored) == ("error", "request_rejected", False)
    assert r.error is not None and "scripted policy exhausted" in r.error
    assert len(run.bodies) == 2  # not retried
    assert (r.steps_used, r.camera_actions, r.model_calls) == (1, 1, 1)
    assert read_result(tmp_path) == r


def test_compaction_inside_an_episode_is_logged_and_the_episode_goes_on(pool, tmp_path):
    """A context bound so small that every step from the second compacts: each compaction is
    one summary call (its reply consumed from the script), logged as a "compaction" event
    with the step it happened at, and the episode ends as the model decided (defect B: the
    engine passed `step` twice and every long episode ended as a harness error)."""
    limits = ContextLimits(
        window_tokens=8_292, output_reserve_tokens=8_192, compact_fraction=1.0, keep_user_turns=1
    )
    script = [camera("view_topdown"), "summary one", move("z", "+", 10), "summary two", STOP]
    run = run_scripted(
        TASK,
        script,
        pool,
        seed=SEED,
        out_dir=tmp_path,
        settings=EngineSettings(limits=limits),
    )
    r = run.result
    assert (r.status, r.stop_reason) == ("failure", "model_stop"), r.error
    assert (r.compactions, r.model_calls, r.steps_used) == (2, 5, 2)
    compactions = [e for e in read_events(tmp_path) if e["type"] == "compaction"]
    assert [e["step"] for e in compactions] == [2, 3]
    assert [e["summary"] for e in compactions] == ["summary one", "summary two"]
    assert all(e["messages_summarised"] >= 2 for e in compactions)
    _check_records(run, tmp_path)


def test_the_command_line_prints_no_dollars_for_a_model_without_prices(tmp_path):
    """`python -m vabench.episode` printed `$0.0000` for every model: the embedded
    server reads "no cost (embedded server)"."""
    cmd = [
        *(sys.executable, "-m", "vabench.episode"),
        *("--task", TASK, "--seed", str(SEED), "--backend", "c"),
        *("--width", "64", "--height", "48", "--max-steps", "2"),
        *("--out", str(tmp_path / "episode")),
    ]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    last = [line for line in proc.stdout.splitlines() if "output tokens" in line][-1]
    assert "no cost (embedded server)" in last and "$" not in last
