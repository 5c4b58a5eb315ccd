"""The engine benchmark's several-process rows (benchmarks/engine.py `--processes`,
benchmarks/engine_rounds.py): a round's episodes dealt over real engine processes (C MuJoCo,
the GL pool, the embedded server over loopback HTTP), started together, every decision counted
once, against the same round in one process; a process that fails or dies before the start ends
the round at once with its reason."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import engine_rounds

ROOT = Path(__file__).resolve().parents[1]


def test_episodes_are_dealt_over_the_processes_as_evenly_as_they_go():
    assert engine_rounds.shares(1000, 4) == [250] * 4
    assert engine_rounds.shares(10, 4) == [3, 3, 2, 2]
    assert sum(engine_rounds.shares(2001, 3)) == 2001
    assert engine_rounds.shares(2, 4) == [1, 1, 0, 0]


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
    # the parent's clock spans the processes' own rounds (it starts them together) and no more
    # (their start-up and warm-up, seconds here, are before it)
    walls = two["process_walls_s"]
    assert max(walls) - 0.05 <= two["wall_s"] <= max(walls) + 1.0, (two["wall_s"], walls)
    assert two["sim_calls"] >= 2 * 2  # each process steps its own batch: two calls at least
    assert "several engine processes" in run.stdout


def test_more_processes_than_episodes_is_refused_naming_the_option():
    with pytest.raises(SystemExit, match="--processes 4"):
        engine_rounds.run_in_processes({}, {}, 2, 4, 0.01)


OPTIONS = dict(
    task="grasp_single_cube",
    renderer="gl",
    render_workers=1,
    platform="auto",
    size=(96, 72),
    steps=1,
    latency=0.1,
    batch_kwargs={"backend": "c"},
)
ENDPOINT = {"name": "local", "api": "openai_chat", "base_url": "http://127.0.0.1:9/v1"}


def _round_end(monkeypatch, *args) -> str:
    """How `run_in_processes(*args)` ends (its SystemExit's message) when its start has no
    timeout at all: a round that ends did so because the failure was seen, never because a
    timeout ran out (an order, not a time). It runs in a thread: the join only keeps a start
    that waits for ever from hanging the suite."""
    monkeypatch.setattr(engine_rounds, "START_TIMEOUT_S", None)  # the barrier waits for ever
    ended: list[str] = []

    def round_() -> None:
        try:
            engine_rounds.run_in_processes(*args)
        except SystemExit as err:
            ended.append(str(err))

    thread = threading.Thread(target=round_, daemon=True)
    thread.start()
    thread.join(600)
    assert ended, "the round still waits for its start"
    return ended[0]


def test_a_process_that_fails_before_the_start_ends_the_round_with_its_reason(monkeypatch):
    said = _round_end(monkeypatch, {**OPTIONS, "task": "no_such_task"}, ENDPOINT, 2, 2, 0.01)
    assert re.search(r"did not start: .*no_such_task", said), said


def test_a_process_that_dies_without_a_word_before_the_start_ends_the_round(monkeypatch):
    """An interpreter that cannot start (as a native crash or an OOM kill would end one) says
    nothing: the watch on the processes breaks the start for the others."""
    said = _round_end(monkeypatch, OPTIONS, ENDPOINT, 2, 2, 0.01, {"PYTHONHOME": "/nonexistent"})
    assert re.search(r"did not start: engine-\d exited", said), said
