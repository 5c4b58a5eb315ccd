"""The sweep's front door: what the real run refuses, `--dry-run` refuses too, in one line.

Seen by a new user (issue 34): `--out` naming a file ended in a FileExistsError traceback, and
the same with `--dry-run` exited 0 saying nothing; a dry-run after a change to the plan
(`step_budget` 5 -> 6) printed "8 of 8 episodes already finished" while the real run refused.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from vabench.config import load_config
from vabench.sweep.__main__ import main
from vabench.sweep.plan import plan
from vabench.sweep.rundir import check_run_dir

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"


@pytest.mark.parametrize("dry_run", [False, True])
def test_out_naming_a_file_is_one_clear_line(tmp_path, capsys, dry_run):
    target = tmp_path / "a_file"
    target.write_text("not a run directory")
    argv = [str(SMOKE), "--out", str(target), "--plain", *(["--dry-run"] if dry_run else [])]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"the run directory {target} is a file" in err
    assert "Traceback" not in err and "FileExistsError" not in err
    assert target.read_text() == "not a run directory"


def test_dry_run_refuses_a_changed_plan_like_the_run(tmp_path, capsys):
    out = tmp_path / "run"
    config = load_config(SMOKE, overrides={"out": str(out)})
    check_run_dir(out, config, plan(config), config.document())  # a run directory of smoke
    changed = yaml.safe_load(SMOKE.read_text())
    changed["step_budget"] = int(changed["step_budget"]) + 1
    edited = tmp_path / "smoke_6.yaml"
    edited.write_text(yaml.safe_dump(changed))
    assert main([str(edited), "--out", str(out), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "different plan" in err and "step_budget" in err


def test_dry_run_of_a_new_or_matching_run_directory_still_passes(tmp_path, capsys):
    out = tmp_path / "run"
    assert main([str(SMOKE), "--out", str(out), "--dry-run"]) == 0
    assert not out.exists()  # a dry run writes nothing
    config = load_config(SMOKE, overrides={"out": str(out)})
    check_run_dir(out, config, plan(config), config.document())
    assert main([str(SMOKE), "--out", str(out), "--dry-run"]) == 0
