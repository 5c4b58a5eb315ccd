"""The driver weighs an episode by the seconds this machine measured an episode of its task
(`cells.episode_costs`), the step budget where none was measured: a sweep's end keeps each
task's seconds in the pace file, the next sweep's plan deals by them, and no plan mixes seconds
with steps."""

from __future__ import annotations

import dataclasses
import json
import logging

import pytest

from vabench.check import pace
from vabench.check.pace import keep_pace, machine_paces, measure_kinds, model_kind
from vabench.config import load_config
from vabench.config.choices import choose
from vabench.machine_cache import write_host
from vabench.sweep.cells import dealing_line, episode_costs, pending_cells
from vabench.sweep.plan import plan
from vabench.sweep.process_executor import ProcessEngines, plan_chunks

TASKS = ["grasp_single_cube", "handover_horizontal_block", "lift_pot", "place_shoe"]
CONFIG = f"""\
name: dealing
models:
  - {{name: local, api: openai_chat, base_url: embedded}}
embedded_server: {{policy: conversation_hash}}
tracks: [active, passive]
tasks: [{", ".join(TASKS)}]
seeds: {{verified: 4}}
runs: 1
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
executor: {{kind: processes, max_tasks: 2}}
"""


@pytest.fixture
def config(tmp_path):
    (tmp_path / "c.yaml").write_text(CONFIG)
    return load_config(tmp_path / "c.yaml")


def ledger(run_dir, walls: dict[str, list[float]], model: str = "local") -> None:
    """A run directory whose ledger holds episodes of `walls` (seconds by task), one after
    another."""
    run_dir.mkdir(parents=True)
    lines, t = [], 1000.0
    for task, seconds in walls.items():
        for seed, wall in enumerate(seconds):
            record = {"model": model, "track": "active", "task": task, "seed": seed, "run": 0}
            lines.append(json.dumps(record | {"started_at": t, "wall_s": wall, "steps_used": 3}))
            t += wall
    (run_dir / "results.jsonl").write_text("\n".join(lines) + "\n")


def test_a_sweeps_end_keeps_each_tasks_seconds_an_episode(config, tmp_path):
    ledger(tmp_path / "run", {"lift_pot": [4.0, 6.0], "grasp_single_cube": [1.0]})
    (measured,) = measure_kinds(tmp_path / "run", config)
    assert measured.task_seconds == {"grasp_single_cube": 1.0, "lift_pot": 5.0}
    keep_pace(tmp_path / "run", config)
    kept = machine_paces()[model_kind(config, "local")]
    assert kept.task_seconds == {"grasp_single_cube": 1.0, "lift_pot": 5.0}


def test_a_pace_kept_before_tasks_were_measured_still_reads(config, tmp_path):
    ledger(tmp_path / "run", {"lift_pot": [4.0]})
    (measured,) = measure_kinds(tmp_path / "run", config)
    old = {k: v for k, v in dataclasses.asdict(measured).items() if k != "task_seconds"}
    pace.pace_file().parent.mkdir(parents=True, exist_ok=True)
    write_host(pace.pace_file(), {measured.kind: old})
    (read,) = machine_paces().values()
    assert read.task_seconds == {} and read.decisions == measured.decisions
    assert episode_costs(config, TASKS, machine_paces()) == {
        t: float(config.budget(t)) for t in TASKS
    }


def test_measured_seconds_weigh_an_episode_and_the_rest_follow_their_budgets(config, tmp_path):
    budgets = {t: config.budget(t) for t in TASKS}
    assert episode_costs(config, TASKS, {}) == {t: float(b) for t, b in budgets.items()}
    assert "step budgets" in dealing_line(config, TASKS, {})

    ledger(tmp_path / "run", {"lift_pot": [30.0], "grasp_single_cube": [2.0, 4.0]})
    paces = {p.kind: p for p in measure_kinds(tmp_path / "run", config)}
    costs = episode_costs(config, TASKS, paces)
    assert costs["lift_pot"] == 30.0 and costs["grasp_single_cube"] == 3.0
    per_step = 33.0 / (budgets["lift_pot"] + budgets["grasp_single_cube"])
    for task in ("handover_horizontal_block", "place_shoe"):
        assert costs[task] == pytest.approx(budgets[task] * per_step)
    assert "2 of 4 tasks measured" in dealing_line(config, TASKS, paces)

    # another model kind's seconds say nothing of this one's
    other = tmp_path / "other.yaml"
    other.write_text(CONFIG.replace("conversation_hash", "reference_servo"))
    assert episode_costs(load_config(other), TASKS, paces) == {
        t: float(b) for t, b in budgets.items()
    }


def test_engine_processes_are_dealt_tasks_by_measured_seconds(config, tmp_path, caplog):
    """Batched physics, two engine processes: budgets deal handover + grasp against shoe + pot
    (100 + 50 steps a pair); where the pot measured ten times the others' seconds, it gets a
    chunk to itself, and the driver's chunks carry the seconds."""
    choices = choose(config)
    batched = dataclasses.replace(
        choices,
        physics=dataclasses.replace(choices.physics, kind=type(choices.physics.kind)("mjx")),
    )
    cells = pending_cells(plan(config), set())
    by_budget = [{k.task for k in part} for _, part in plan_chunks(config, cells, batched)]
    assert {"lift_pot"} not in by_budget

    walls = {t: [10.0] for t in TASKS} | {"lift_pot": [100.0]}
    ledger(tmp_path / "run", walls)
    keep_pace(tmp_path / "run", config)
    with caplog.at_level(logging.INFO, logger="vabench.sweep"):
        engines = ProcessEngines(config, batched, tmp_path, cells)
    assert "4 of 4 tasks measured" in caplog.text
    dealt = [{k.task for k in c.keys} for c in engines.chunks]
    assert dealt[0] == {"lift_pot"} and len(dealt) == 2
    assert {c.cost for c in engines.chunks if "lift_pot" in {k.task for k in c.keys}} == {100.0}
    assert sorted(k for c in engines.chunks for k in c.keys) == sorted(
        k for keys in cells.values() for k in keys
    )
