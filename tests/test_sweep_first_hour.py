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


def test_only_what_an_engine_needs_travels_to_a_ray_cluster(tmp_path):
    """A checkout with a second venv (1.46 GB) passed Ray's 512 MiB upload limit: the package,
    configs and assets travel, nothing else; read by Ray's own packaging."""
    packaging = pytest.importorskip("ray._private.runtime_env.packaging")
    import zipfile

    from vabench.sweep.ray_plan import ship_excludes

    root = tmp_path / "checkout"
    for name in ("vabench/sweep", "vabench/__pycache__", "configs/seeds", "assets", "venv/lib"):
        (root / name).mkdir(parents=True)
    for name in (
        "pyproject.toml",
        "vabench/__init__.py",
        "vabench/sweep/run.py",
        "vabench/__pycache__/x.pyc",
        "configs/smoke.yaml",
        "configs/seeds/a.json",
        "assets/scene.xml",
        "venv/lib/big.so",
        "README.md",
    ):
        (root / name).write_text("x")
    for name in ("runs/smoke", ".cache/warp", ".git", "tests", "docs"):
        (root / name).mkdir(parents=True)
        (root / name / "f").write_text("x")
    zipped = tmp_path / "pkg.zip"
    packaging._zip_files(str(root), ship_excludes(root), str(zipped), include_gitignore=False)
    names = sorted(n for n in zipfile.ZipFile(zipped).namelist() if not n.endswith("/"))
    assert names == [
        "assets/scene.xml",
        "configs/seeds/a.json",
        "configs/smoke.yaml",
        "pyproject.toml",
        "vabench/__init__.py",
        "vabench/sweep/run.py",
    ]


def test_an_upload_failure_is_one_line_with_cause_and_fix():
    from vabench.sweep.ray_plan import upload_failure

    err = RuntimeError(
        "Failed to upload working_dir /home/u/vabench to the cluster.\n"
        "Package size (1457.94MiB) exceeds the maximum size of 512.00MiB. You can exclude "
        "large files using the 'excludes' option to the runtime_env."
    )
    line = upload_failure(err)
    assert "\n" not in line and line.startswith("ray: the checkout could not be uploaded")
    assert "1457.94MiB" in line and "vabench, configs, assets, pyproject.toml" in line
    assert "pip install ." in line


TINY = """\
name: tiny
models:
  - {name: local, api: openai_chat, base_url: embedded}
embedded_server: {policy: random_action}
tracks: [{name: active, protocol: active, summaries: none}]
tasks: [grasp_single_cube]
seeds: {verified: 2}
runs: 1
step_budget: 2
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
records: {frames: FRAMES}
"""


def _tiny(tmp_path: Path, frames: str = "all") -> Path:
    cfg = tmp_path / f"tiny_{frames}.yaml"
    cfg.write_text(TINY.replace("FRAMES", frames))
    return cfg


@pytest.mark.parametrize("frames", ["none", "failed"])
def test_records_frames_keeps_the_frames_asked_for(tmp_path, capsys, frames):
    out = tmp_path / "out"
    assert main([str(_tiny(tmp_path, frames)), "--out", str(out), "--plain", "--no-report"]) == 0
    jpegs = list((out / "episodes").rglob("*.jpg"))
    results = list((out / "episodes").rglob("result.json"))
    assert len(results) == 2  # events and results are always kept
    if frames == "none":
        assert jpegs == []
    else:  # the random actor fails: a failed episode keeps its frames
        assert len(jpegs) >= 2
    # the viewer says which frames the run kept, and why an episode shows none
    from vabench.diagnostics.episodes import RunIndex
    from vabench.view.timeline import build_timeline, frames_kept

    assert frames_kept(out) == frames
    index = RunIndex.load(out)
    timeline = build_timeline(index, next(iter(index.episodes)))
    assert timeline["frames_kept"] == frames
    note = timeline["frames_note"]
    assert (note is not None and "records.frames: none" in note) == (frames == "none")
    assert frames != "failed" or note is None  # a failed episode's frames are there


def test_a_success_keeps_no_frames_under_failed(tmp_path):
    from vabench.agent.records import EpisodeRecorder, EpisodeResult

    def run(success: bool) -> Path:
        d = tmp_path / f"ep_{success}"
        rec = EpisodeRecorder(d, frames="failed")
        rec.frame(0, b"\xff\xd8jpeg")
        status = "success" if success else "failure"
        result = EpisodeResult(
            task="grasp_single_cube", seed=1, model="m", protocol="active", run=1,
            status=status, success=success, stop_reason="success" if success else "budget",
            step_budget=2, n_checkpoints=1,
        )  # fmt: skip
        rec.finish(result)
        return d

    assert not list(run(True).rglob("*.jpg")) and (tmp_path / "ep_True" / "result.json").exists()
    assert len(list(run(False).rglob("*.jpg"))) == 1


@pytest.mark.parametrize("executor", ["local", "processes"])
def test_the_sweep_stops_with_one_line_before_the_disk_is_full(
    tmp_path, capsys, monkeypatch, caplog, executor
):
    """Free disk below the reserve once the first episode is recorded: checked by the one
    driver on each of its ticks and after its last record; the engines ended at once, one line,
    exit 2, the record kept, and the same command resumes without running it again, saying
    so, each episode recorded once, its output directory named at the start and the
    statistics in the run directory's log."""
    import logging
    import re

    from vabench.sweep import rundir

    caplog.set_level(logging.INFO)
    cfg, out = _tiny(tmp_path), tmp_path / "out"
    if executor == "processes":
        cfg.write_text(cfg.read_text() + "executor: {kind: processes, max_tasks: 2}\n")
    real = rundir.disk_short

    def short_after_one(run_dir, reserve=None):
        recorded = (run_dir / "results.jsonl").exists()
        return real(run_dir, reserve=1e18) if recorded else None

    monkeypatch.setattr(rundir, "disk_short", short_after_one)
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("stopped: disk: ") and "resume" in err[0], err
    first = (out / "results.jsonl").read_text().splitlines()
    assert 1 <= len(first) <= 2
    assert f"output:    {out} (new)" in caplog.messages
    monkeypatch.setattr(rundir, "disk_short", real)
    caplog.clear()
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    assert f"output:    {out}" in caplog.messages
    assert any(re.fullmatch(r"resuming:  [12] of 2 already recorded", m) for m in caplog.messages)
    logged = (out / "logs" / "sweep.log").read_text()
    assert "started:" in logged and "resuming:" in logged
    if executor == "local":  # the engine's statistics: in this process's log
        assert "host, whole run" in logged
    lines = (out / "results.jsonl").read_text().splitlines()
    assert lines[: len(first)] == first and len(lines) == 2
