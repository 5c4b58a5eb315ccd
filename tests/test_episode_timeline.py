"""benchmarks/episode_timeline.py on a small run directory whose event times are known: each
interval of a step lands in its phase (every phase a different length, so a mix-up changes a
mean), each timed decision in the window where its step ended, and what is not a step of an
episode's own log (set-aside attempts, a step cut off, a broken line) stays out of the means."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import episode_timeline as timeline

from vabench.agent import records
from vabench.agent.records import EpisodeRecorder
from vabench.run_layout import RunDir

# Times are multiples of 1/4 s, exact in binary, so the means compare exactly.
ALPHA = [  # (t, type): model-a, task alpha, written by the engine's own recorder
    (100.0, "episode_start"),
    (101.0, "reset"),
    # step 1: other 0.5 + 0.25, model 2, physics 4, images 1 -> 7.75 s
    (102.0, "observation"),
    (102.5, "request"),
    (104.5, "reply"),
    (104.75, "decision"),
    (108.75, "action"),
    # step 2, a tool round trip and a camera move: other 0.25 + 0.5 + 0.25 + 0.25 + 0.25,
    # model 1 + 2, physics 0, images 2 -> 6.5 s
    (109.75, "observation"),
    (110.0, "request"),
    (111.0, "reply"),
    (111.5, "tool"),
    (111.75, "request"),
    (113.75, "reply"),
    (114.0, "decision"),
    (114.25, "camera"),
    # step 3, the episode's last decision: no next observation, so no step time
    (116.25, "observation"),
    (116.5, "request"),
    (117.0, "reply"),
    (117.25, "decision"),
    (118.0, "action"),
    (118.25, "end"),
]
BETA = [  # model vendor/b (a name with a slash), task beta, cut off mid-step 2
    (200.0, "episode_start"),
    (201.0, "reset"),
    # step 1 with a compaction (the summary call, model) first: model 3 + 1, other 0.5 + 0.5,
    # physics 2, images 0.5 -> 7.5 s
    (202.0, "observation"),
    (205.0, "compaction"),
    (205.5, "request"),
    (206.5, "reply"),
    (207.0, "decision"),
    (209.0, "action"),
    (209.5, "observation"),
    (210.0, "request"),
]


def _line(seq: int, t: float, kind: str, **fields) -> str:
    return json.dumps({"v": 1, "seq": seq, "t": t, "type": kind, "step": 1, **fields}) + "\n"


def _record(directory: Path, events: list[tuple[float, str]], monkeypatch) -> None:
    """The events as `EpisodeRecorder.event` writes them, its clock scripted."""
    clock = iter(t for t, _ in events)
    monkeypatch.setattr(records, "time", SimpleNamespace(time=lambda: next(clock)))
    rec = EpisodeRecorder(directory)
    for _, kind in events:
        rec.event(kind, step=1)
    rec.close()


@pytest.fixture
def run(tmp_path, monkeypatch) -> Path:
    layout = RunDir(tmp_path / "run")
    alpha = layout.episode("model-a", "active", "alpha", 1, 1)
    _record(alpha.path, ALPHA, monkeypatch)
    # Set aside beside it: an interrupted attempt and a finished one run again, each a whole
    # timed step of other lengths, and an episode that holds only an interrupted attempt.
    step = [(0.0, "observation"), (1.0, "decision"), (50.0, "action"), (51.0, "observation")]
    for aside in ("partial_1", "attempt_1"):
        _record(alpha.path / aside, step, monkeypatch)
    _record(
        layout.episode("model-a", "active", "alpha", 1, 2).path / "partial_1", step, monkeypatch
    )

    beta = layout.episode("vendor/b", "passive", "beta", 7, 1).events
    beta.parent.mkdir(parents=True)
    lines = [_line(seq, t, kind) for seq, (t, kind) in enumerate(BETA)]
    # A line of another key order is read whole; one cut off mid-write is skipped and counted.
    lines[3] = json.dumps({"type": "compaction", "t": 205.0, "step": 1}, sort_keys=True) + "\n"
    lines.append('{"v": 1, "seq": 10, "t": 211.0, "type": "reply", "step": 2, "te')
    beta.write_text("".join(lines))
    return layout.path


def test_phases_add_up_per_task(run):
    out = timeline.summary(timeline.measure(run, window_s=5.0))
    assert out["t0"] == 100.0  # the run's earliest event
    assert out["tasks"]["alpha"] == {
        "episodes": 1,
        "decisions": 2,
        "step_s": (7.75 + 6.5) / 2,
        "physics_s": (4 + 0) / 2,
        "images_s": (1 + 2) / 2,
        "model_s": (2 + 3) / 2,
        "other_s": (0.75 + 1.5) / 2,
        "final": 1,
        "cut": 0,
    }
    assert out["tasks"]["beta"] == {
        "episodes": 1,
        "decisions": 1,
        "step_s": 7.5,
        "physics_s": 2.0,
        "images_s": 0.5,
        "model_s": 4.0,
        "other_s": 1.0,
        "final": 0,
        "cut": 1,
    }
    assert out["all"]["decisions"] == 3
    assert out["all"]["step_s"] == (7.75 + 6.5 + 7.5) / 3
    assert out["bad_lines"] == 1


def test_each_decision_in_the_window_its_step_ended(run):
    out = timeline.summary(timeline.measure(run, window_s=5.0))
    # Steps end at 109.75 and 116.25 (alpha) and 209.5 (beta): windows 1, 3 and 21 from t0.
    windows = {w["start_s"]: w for w in out["windows"]}
    assert list(windows) == [5.0 * k for k in range(1, 22)]
    assert {s: w["decisions"] for s, w in windows.items() if w["decisions"]} == {
        5.0: 1,
        15.0: 1,
        105.0: 1,
    }
    assert windows[5.0]["physics_s"] == 4.0 and windows[5.0]["images_s"] == 1.0
    assert windows[15.0]["model_s"] == 3.0 and windows[15.0]["other_s"] == 1.5
    assert windows[105.0]["step_s"] == 7.5
    assert windows[10.0]["step_s"] is None


def test_tasks_and_t0_select(run):
    # One task read; t0 is still the run's (alpha's start), so beta's step is in window 21.
    out = timeline.summary(timeline.measure(run, {"beta"}, window_s=5.0))
    assert list(out["tasks"]) == ["beta"]
    assert [(w["start_s"], w["decisions"]) for w in out["windows"]] == [(105.0, 1)]
    out = timeline.summary(timeline.measure(run, {"alpha"}, window_s=4.0, t0=109.0))
    assert [(w["start_s"], w["decisions"]) for w in out["windows"]] == [(0.0, 1), (4.0, 1)]
    with pytest.raises(SystemExit, match=r"gamma.*tasks: alpha, beta"):
        timeline.measure(run, {"gamma"})


def test_main_prints_and_writes_json(run, tmp_path, capsys):
    out = tmp_path / "timeline.json"
    assert timeline.main([str(run), "--task", "alpha", "--window", "5", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "alpha" in printed and "beta" not in printed
    assert "7.125" in printed  # alpha's mean step
    written = json.loads(out.read_text())
    assert written["tasks"]["alpha"]["decisions"] == 2
    assert written["windows"][0]["start_s"] == 5.0
