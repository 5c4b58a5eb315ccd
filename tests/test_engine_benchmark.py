"""The engine benchmark's several-process rows (benchmarks/engine.py `--processes`): a round's
episodes dealt over real engine processes (C MuJoCo, the GL pool, the embedded server over
loopback HTTP), started together, every decision counted once, against the same round in one
process."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import engine as engine_benchmark

ROOT = Path(__file__).resolve().parents[1]


def test_episodes_are_dealt_over_the_processes_as_evenly_as_they_go():
    assert engine_benchmark.shares(1000, 4) == [250] * 4
    assert engine_benchmark.shares(10, 4) == [3, 3, 2, 2]
    assert sum(engine_benchmark.shares(2001, 3)) == 2001
    assert engine_benchmark.shares(2, 4) == [1, 1, 0, 0]


def test_a_round_over_two_processes_counts_every_decision_once(tmp_path):
    out = tmp_path / "engine.json"
    run = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "engine.py"), "--json", str(out)]
        + [
            "--backend",
            "c",
            "--renderer",
            "gl",
            "--render-workers",
            "1",
            "--concurrency",
            "4",
            "--processes",
            "1,2",
            "--steps",
            "2",
            "--latency",
            "0.2",
            "--size",
            "96x72",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    one, two = json.loads(out.read_text())
    for row in (one, two):
        assert row["concurrency"] == 4 and row["errors"] == 0, row["error_examples"]
        assert row["decisions"] == 4 * 2  # each episode's two decisions, once
    assert (one["processes"], two["processes"]) == (1, 2)
    assert len(two["process_walls_s"]) == 2
    # the parent's clock spans the processes' own rounds (it starts them together)
    assert two["wall_s"] >= max(two["process_walls_s"]) - 0.05
    assert two["sim_mean_batch"] <= 2  # each process its own batch of two slots
    assert "several engine processes" in run.stdout


def test_more_processes_than_episodes_is_refused_naming_the_option(tmp_path):
    with pytest.raises(SystemExit, match="--processes 4"):
        engine_benchmark.run_in_processes({}, {}, 2, 4, 0.01)
