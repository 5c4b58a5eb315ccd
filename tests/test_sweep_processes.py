"""`executor: processes`: the cells of a sweep as spawned worker processes of one host end with
the same records as the local executor; a rerun runs nothing; a failing cell is reported while
the others finish. The model is `conversation_hash` (decisions depend on each episode's own
conversation only), so where and in which order episodes run cannot change them."""

from __future__ import annotations

import json
import logging
import pstats

from vabench.config import load_config
from vabench.sweep.__main__ import main
from vabench.sweep.choices import choose
from vabench.sweep.plan import EpisodeKey, plan
from vabench.sweep.process_executor import PROFILE_VARIABLE, run_processes

CONFIG = """\
name: processes
models:
  - {{name: local, api: openai_chat, base_url: embedded}}
embedded_server: {{policy: conversation_hash}}
tracks: [active]
tasks: [grasp_single_cube, handover_horizontal_block]
seeds: {{verified: 2}}
runs: 1
step_budget: 3
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
executor: {executor}
"""
TIMING = {"wall_s", "started_at"}


def records(run_dir):
    out = {}
    for line in (run_dir / "results.jsonl").read_text().splitlines():
        r = json.loads(line)
        key = (r["model"], r["track"], r["task"], r["seed"], r["run"])
        assert key not in out, f"two records for {key}"
        out[key] = {k: v for k, v in r.items() if k not in TIMING}
    return out


def test_processes_equal_the_local_executor_and_a_rerun_runs_nothing(tmp_path, caplog):
    local = tmp_path / "local.yaml"
    local.write_text(CONFIG.format(executor="{max_tasks: 2}"))
    assert main([str(local), "--out", str(tmp_path / "local"), "--plain", "--no-report"]) == 0
    cfg = tmp_path / "processes.yaml"
    cfg.write_text(CONFIG.format(executor="{kind: processes, max_tasks: 2}"))
    out = tmp_path / "processes"
    with caplog.at_level(logging.INFO, logger="vabench.sweep.process_executor"):
        assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    assert "cells 2/2 done (0 failed) | episodes recorded 4/4" in caplog.text
    assert records(out) == records(tmp_path / "local") and len(records(out)) == 4
    # summaries were learned once per family, in the cells' processes
    assert sorted(p.name for p in (out / "summaries" / "local").glob("*.json")) == [
        "grasp_single_cube.json",
        "handover_horizontal_block.json",
    ]
    ledger = (out / "results.jsonl").read_bytes()
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="vabench.sweep.process_executor"):
        assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    assert "nothing to run" in caplog.text
    assert (out / "results.jsonl").read_bytes() == ledger


def test_a_failing_cell_is_reported_and_the_others_finish(tmp_path, caplog):
    path = tmp_path / "processes.yaml"
    path.write_text(CONFIG.format(executor="{kind: processes, max_tasks: 2}"))
    run_dir = tmp_path / "out"
    config = load_config(path, overrides={"tasks": ["grasp_single_cube"], "out": str(run_dir)})
    keys = [*plan(config), EpisodeKey("local", "active", "no_such_task", 1, 1)]
    run_dir.mkdir()
    (run_dir / "plan.json").write_text(json.dumps([k.as_id() for k in keys]))
    with caplog.at_level(logging.INFO, logger="vabench.sweep.process_executor"):
        got = run_processes(config, keys, run_dir, choose(config))
    assert sorted(got) == sorted(
        (k.model, k.track, k.task, k.seed, k.run) for k in keys if k.task != "no_such_task"
    )
    assert "cell local/active/no_such_task failed" in caplog.text
    assert "1 of 2 cells failed: local/active/no_such_task" in caplog.text


def test_workers_write_a_profile_of_each_chunk_when_asked(tmp_path, monkeypatch):
    """VABENCH_PROFILE_DIR: each worker leaves a cProfile of its chunk (how a GPU host without
    a sampling profiler shows where a worker's time goes)."""
    path = tmp_path / "processes.yaml"
    path.write_text(CONFIG.format(executor="{kind: processes, max_tasks: 1}"))
    run_dir, folder = tmp_path / "out", tmp_path / "profiles"
    config = load_config(path, overrides={"tasks": ["grasp_single_cube"], "out": str(run_dir)})
    keys = plan(config)
    run_dir.mkdir()
    (run_dir / "plan.json").write_text(json.dumps([k.as_id() for k in keys]))
    monkeypatch.setenv(PROFILE_VARIABLE, str(folder))
    assert len(run_processes(config, keys, run_dir, choose(config))) == len(keys)
    (profile,) = folder.glob("*.prof")
    assert "local-active-grasp_single_cube" in profile.name
    functions = {name for _, _, name in pstats.Stats(str(profile)).stats}  # type: ignore[attr-defined]
    assert {"_run_reporting", "open_engine", "_run_task"} <= functions  # the chunk's engine
