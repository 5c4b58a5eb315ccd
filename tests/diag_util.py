"""A real run directory for the diagnostics and viewer tests: the smoke config (configs/smoke.yaml:
the embedded server's random actor, C MuJoCo, small images) cut to one task and one seed so
it runs in seconds, both tracks (a single image per step and the passive five-view bundle),
made once per test process by the real sweep command; each test gets its own copy."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
_PRISTINE: dict[str, Path] = {}


def smoke_run(base: Path) -> Path:
    """The pristine run (made on first use under `base`); never write into it."""
    if "run" not in _PRISTINE:
        config = yaml.safe_load((REPO / "configs" / "smoke.yaml").read_text())
        config.update(tasks=["grasp_single_cube"], seeds={"verified": 1}, step_budget=4)
        # the random actor at small images (the smoke config runs the reference agent): a
        # run of seconds whose episodes fail, as these tests read them
        config.update(
            models=[{"name": "local", "api": "openai_chat", "base_url": "embedded"}],
            embedded_server={"policy": "random_action"},
            tracks=["active", "passive"],
            render={"width": 320, "height": 240, "workers": 1},
        )
        path = base / "smoke.yaml"
        path.write_text(yaml.safe_dump(config))
        out = base / "run"
        subprocess.run(
            [
                sys.executable,
                "-m",
                "vabench.sweep",
                str(path),
                "--out",
                str(out),
                "--plain",
                "--no-report",
            ],
            cwd=REPO,
            check=True,
            timeout=600,
            capture_output=True,
        )
        _PRISTINE["run"] = out
    return _PRISTINE["run"]


def copy_run(base: Path, dest: Path) -> Path:
    return Path(shutil.copytree(smoke_run(base), dest))


ACTIVE = "local/active/grasp_single_cube/seed_1000/run_1"
PASSIVE = "local/passive/grasp_single_cube/seed_1000/run_1"
