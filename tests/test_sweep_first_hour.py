"""A newcomer's first hour with the sweep command: flags written in full, every error in one
form ("error: WHAT: WHY; FIX"), hints that are true, the choices and the output directory
said once at the start."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from vabench.sweep.__main__ import main

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"


def test_an_abbreviated_flag_is_refused_with_did_you_mean(tmp_path):
    """Through the command a user types: `--seed 2` was taken silently as `--seeds 2`."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "vabench.sweep", str(SMOKE), "--dry-run", "--out", str(out)]
        + ["--seed", "2"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert lines == [
        "error: --seed: unknown flag (flags are written in full); did you mean --seeds?"
    ]
    assert "Planned episodes" not in done.stdout and not out.exists()


@pytest.mark.parametrize(
    "flags, expected",
    [
        (["--runs", "0"], "runs: must be at least 1, got 0 (from --runs 0)"),
        (["--runs", "x"], "runs: must be a whole number, got 'x' (from --runs x)"),
        (["--runs"], "error: --runs: expected one argument; see --help"),
        (["--plian"], "error: --plian: unknown flag (flags are written in full); did you mean"),
    ],
)
def test_every_error_is_one_line_in_one_form(tmp_path, capsys, flags, expected):
    argv = [str(SMOKE), "--dry-run", "--out", str(tmp_path / "out"), *flags]
    try:
        status = main(argv)
    except SystemExit as exit_:  # argparse's errors leave through exit(2)
        status = exit_.code
    assert status == 2
    err = capsys.readouterr().err
    (line,) = err.strip().splitlines()
    assert line.startswith("error: ") and expected in line
    assert "Input should" not in line and "usage:" not in line
