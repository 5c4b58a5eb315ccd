"""The replay CLI, run as a user runs it (a real subprocess), on both backends."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

ACTIONS = [
    {"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 60},
    {"action": "gripper.move_world", "axis": "z", "sign": "+", "distance_mm": 500},
    {"action": "gripper.close"},
]


@pytest.mark.parametrize("backend", ["c", pytest.param("mjx", marks=pytest.mark.slow)])
def test_replay_cli(tmp_path, backend):
    path = tmp_path / "actions.json"
    path.write_text(json.dumps(ACTIONS))
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "vabench.replay",
            "--task",
            "probe_cube",
            "--seed",
            "5",
            "--actions",
            str(path),
            "--json",
            "--backend",
            backend,
        ],
        capture_output=True,
        text=True,
        timeout=600,
        env=os.environ.copy(),
        check=True,
    )
    doc = json.loads(out.stdout)
    assert doc["task"] == "probe_cube" and doc["seed"] == 5
    steps = doc["steps"]
    assert len(steps) == 4 and "action" not in steps[0]
    assert set(steps[0]["objects"]) == {"cube"}
    assert set(steps[0]["proprio"]["right"]) >= {
        "is_open",
        "finger_center_xyz",
        "control_eepose_xyz",
        "control_eepose_rpy_deg",
        "control_eepose_quat",
        "local_axes_world",
    }
    dz = (
        steps[1]["proprio"]["right"]["finger_center_xyz"][2]
        - steps[0]["proprio"]["right"]["finger_center_xyz"][2]
    )
    assert dz == pytest.approx(-0.060, abs=0.002)
    assert steps[1]["planner_success"] and steps[1]["valid"]
    assert not steps[2]["valid"] and "distance_mm" in steps[2]["error"]
    assert steps[3]["proprio"]["right"]["is_open"] is False
    assert steps[3]["success"] is False


def test_replay_rejects_unknown_task(tmp_path):
    path = tmp_path / "a.json"
    path.write_text("[]")
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "vabench.replay",
            "--task",
            "nope",
            "--seed",
            "1",
            "--actions",
            str(path),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 2 and "valid tasks" in out.stderr
