"""`executor: processes`: the cells of a sweep as spawned worker processes of one host end with
the same records as the local executor; a rerun runs nothing; a failing cell is reported while
the others finish. The model is `conversation_hash` (decisions depend on each episode's own
conversation only), so where and in which order episodes run cannot change them."""

from __future__ import annotations

import json
import logging
import pstats
import re

from vabench import switches
from vabench.config import load_config
from vabench.config.choices import choose
from vabench.sweep.__main__ import main
from vabench.sweep.plan import EpisodeKey, plan
from vabench.sweep.process_executor import run_processes

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
    with caplog.at_level(logging.INFO, logger="vabench.sweep"):
        assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    assert re.search(
        r"processes: chunks 2/2 done \(0 failed\), 0 running on \d engines \| episodes "
        r"recorded 4/4",
        caplog.text,
    ), caplog.text
    assert records(out) == records(tmp_path / "local") and len(records(out)) == 4
    # each worker's own INFO lines (lost before: a spawned process has no logging set up)
    logs = "".join(p.read_text() for p in (out / "logs").glob("worker_*.log"))
    for task in ("grasp_single_cube", "handover_horizontal_block"):
        assert f"{task}: physics " in logs and "images" in logs  # the stage lines
    assert "engine process: its first chunk" in logs  # its start-up, timed from its spawn
    assert "started:   " in caplog.text  # the sweep's own start-up line
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
    assert "chunk local/active/no_such_task failed" in caplog.text
    assert "1 chunks failed (1 episodes not run): local/active/no_such_task" in caplog.text


def test_workers_write_a_profile_of_each_chunk_when_asked(tmp_path, monkeypatch):
    """VABENCH_PROFILE_DIR: each engine process leaves a cProfile of its life, named after its
    first chunk (how a GPU host without a sampling profiler shows where its time goes)."""
    path = tmp_path / "processes.yaml"
    path.write_text(CONFIG.format(executor="{kind: processes, max_tasks: 1}"))
    run_dir, folder = tmp_path / "out", tmp_path / "profiles"
    config = load_config(path, overrides={"tasks": ["grasp_single_cube"], "out": str(run_dir)})
    keys = plan(config)
    run_dir.mkdir()
    (run_dir / "plan.json").write_text(json.dumps([k.as_id() for k in keys]))
    monkeypatch.setenv(switches.variable("profile_dir"), str(folder))
    assert len(run_processes(config, keys, run_dir, choose(config))) == len(keys)
    (profile,) = folder.glob("*.prof")
    assert "local-active-grasp_single_cube" in profile.name
    functions = {name for _, _, name in pstats.Stats(str(profile)).stats}  # type: ignore[attr-defined]
    assert {"run_chunk", "open_engine", "_run_task"} <= functions  # the chunk's engine


def test_batched_physics_deals_whole_tasks_over_the_workers_each_running_all_of_its(tmp_path):
    """Engine processes sharing a GPU (`executor: processes` on batched physics): each takes
    whole tasks, every track and run (one simulator batch per task), the costliest tasks
    spread first, and steps all of its tasks at once; nothing lost or doubled."""
    import dataclasses

    from vabench.children import CORES_VARIABLE
    from vabench.sim_mjx.warp.device import GPU_SHARE
    from vabench.sweep.cells import dealt_choices, pending_cells
    from vabench.sweep.chunk_engine import for_chunk
    from vabench.sweep.process_executor import (
        ProcessEngines,
        critical_environment,
        critical_tasks,
        plan_chunks,
        worker_shares,
    )
    from vabench.sweep.results import ledger_key
    from vabench.tuning import mps

    text = CONFIG.format(executor="{kind: processes, max_tasks: 2}")
    text = text.replace("tracks: [active]", "tracks: [active, passive]")
    text = text.replace(
        "tasks: [grasp_single_cube, handover_horizontal_block]",
        "tasks: [grasp_single_cube, handover_horizontal_block, lift_pot, place_shoe, "
        "put_everything_in_basket]",
    )
    text = text.replace("step_budget: 3\n", "")  # the tasks' own budgets: the basket's is 5x
    (tmp_path / "c.yaml").write_text(text)
    config = load_config(tmp_path / "c.yaml")
    keys = plan(config)
    choices = choose(config)
    batched = dataclasses.replace(
        choices,
        physics=dataclasses.replace(choices.physics, kind=type(choices.physics.kind)("mjx")),
    )
    assert batched.physics.batched and not choices.physics.batched
    cells = pending_cells(keys, set())

    assert len(plan_chunks(config, cells, batched)) == 2  # no MPS: the 2 asked for, no more
    batched = dataclasses.replace(  # engine processes sharing a GPU under MPS
        batched, executor=dataclasses.replace(batched.executor, mps=True, per_gpu=2)
    )
    parts = plan_chunks(config, cells, batched)
    assert len(parts) == 3
    tasks_of = [{k.task for k in part} for _, part in parts]
    # under MPS the basket (250 steps, at least twice every other budget) is the critical
    # path: an engine process of its own, beside the 2 asked for; the rest by cost (episodes x step
    # budget): handover and shoe 4 x 100, the others 4 x 50, dealt longest first to the
    # cheaper chunk: 600 and 600
    assert parts[0] == ("put_everything_in_basket", parts[0][1])
    assert tasks_of[0] == {"put_everything_in_basket"}
    assert tasks_of[1] == {"handover_horizontal_block", "grasp_single_cube"}
    assert tasks_of[2] == {"place_shoe", "lift_pot"}
    assert parts[1][0] == "+".join(sorted(tasks_of[1], key=parts[1][0].index))
    for _, part in parts:  # every track of a task in the same chunk
        for task in {k.task for k in part}:
            assert {k.track for k in part if k.task == task} == {"active", "passive"}
    flat = [ledger_key(k) for _, part in parts for k in part]
    assert sorted(flat) == sorted(ledger_key(k) for k in keys)
    # each worker's share of the host and the GPU: the basket's own process is not counted
    host = dataclasses.replace(batched, machine=dataclasses.replace(batched.machine, cores=16))
    assert worker_shares(host, len(parts)) == {CORES_VARIABLE: "8", GPU_SHARE: "2"}
    alone = dataclasses.replace(
        batched, executor=dataclasses.replace(batched.executor, max_tasks=1)
    )
    assert len(plan_chunks(config, cells, alone)) == 1  # one process: nothing set apart
    four_tasks = [k for _, part in parts[1:] for k in part]
    assert for_chunk(batched, four_tasks).executor.max_tasks == 4  # every task of it at once
    assert for_chunk(batched, parts[0][1]).executor.max_tasks == 2  # never lowered
    # the critical path as the parent found it, in every engine (each sees only its tasks)
    critical = critical_tasks(config, cells, batched)
    assert critical == {"put_everything_in_basket"}
    told = ProcessEngines(config, host, tmp_path, cells).sent
    for _, part in parts:
        assert for_chunk(told, part).executor.critical_path == ("put_everything_in_basket",)
    # the basket's process: a normal MPS client with half the host's cores for its server;
    # the others stay below normal with their share (the shared environment)
    shared = worker_shares(host, len(parts)) | {mps.PRIORITY_VARIABLE: mps.BELOW_NORMAL}
    assert critical_environment(host, shared, parts[0][1], critical) == {
        mps.PRIORITY_VARIABLE: mps.NORMAL,
        CORES_VARIABLE: "8",
    }
    for _, part in parts[1:]:
        assert critical_environment(host, shared, part, critical) == {}
    assert critical_tasks(config, cells, alone) == set()  # one process: nothing set apart
    no_mps = dataclasses.replace(batched, executor=dataclasses.replace(batched.executor, mps=False))
    assert critical_tasks(config, cells, no_mps) == set()  # one engine process per GPU
    # ... but every engine of batched physics is told the sweep's critical path
    assert dealt_choices(config, cells, no_mps).executor.critical_path == (
        "put_everything_in_basket",
    )
    told = ProcessEngines(config, no_mps, tmp_path, cells).sent
    assert for_chunk(told, parts[1][1]).executor.critical_path == ("put_everything_in_basket",)
    assert dealt_choices(config, cells, choices) is choices  # C MuJoCo: no batches

    # C MuJoCo: cells cut as before, one (model, track, task) each at most
    cut = plan_chunks(config, cells, choices)
    assert all(len({(k.track, k.task) for k in part}) == 1 for _, part in cut)
    assert for_chunk(choices, cut[0][1]) is choices
