"""The sweep's front door: what the real run refuses, `--dry-run` refuses too, in one line.

Seen by a new user: `--out` naming a file ended in a FileExistsError traceback, and
the same with `--dry-run` exited 0 saying nothing; a dry-run after a change to the plan
(`step_budget` 5 -> 6) printed "8 of 8 episodes already finished" while the real run refused.
"""

from __future__ import annotations

import json
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
    changed["step_budget"] = 5  # the tasks' own budgets before
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


KEYED = """\
name: keyed
models:
  - {name: local, api: anthropic, base_url: embedded, api_key_env: VABENCH_DOOR_KEY}
embedded_server: {policy: conversation_hash, api_key: right-key}
tracks: [active]
tasks: [grasp_single_cube]
seeds: {verified: 2}
runs: 1
step_budget: 2
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
"""


def test_dry_run_warns_of_a_missing_key_and_prints_the_plan(tmp_path, capsys, monkeypatch):
    """Issue 34: `--dry-run` refused to print anything until every key was exported, so nobody
    could preview a plan before setting keys. Now a missing key is one warning line naming the
    model and the variable; the real run still refuses at start, with today's message."""
    monkeypatch.delenv("VABENCH_DOOR_KEY", raising=False)
    cfg = tmp_path / "keyed.yaml"
    cfg.write_text(KEYED)
    out = tmp_path / "out"
    assert main([str(cfg), "--out", str(out), "--dry-run"]) == 0
    got = capsys.readouterr()
    assert "Planned episodes: 2" in got.out and "Runs with:" in got.out
    (warning,) = [line for line in got.err.splitlines() if "VABENCH_DOOR_KEY" in line]
    assert warning.startswith("warning: model 'local': environment variable VABENCH_DOOR_KEY")

    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    unset = "environment variable VABENCH_DOOR_KEY is not set"
    assert err == [f"error: {cfg}: models[0].api_key_env: {unset}"]
    assert not out.exists()


def test_a_dotenv_beside_the_config_gives_keys_named_never_shown(tmp_path, capsys, monkeypatch):
    """Issue 34: keys from a `.env` file beside the config (comments, `export`, quotes); the
    dry run names the variables it took from it, never a value; the environment wins."""
    for name in ("VABENCH_DOOR_KEY", "VABENCH_DOOR_OTHER"):  # the run sets them: restored after
        monkeypatch.delenv(name, raising=False)
    cfg = tmp_path / "keyed.yaml"
    cfg.write_text(KEYED)
    (tmp_path / ".env").write_text(
        '# keys for the trials\n\nexport VABENCH_DOOR_KEY = "right-key"\n'
        "VABENCH_DOOR_OTHER='x y' # unused\n"
    )
    out = tmp_path / "out"
    assert main([str(cfg), "--out", str(out), "--dry-run"]) == 0
    got = capsys.readouterr()
    assert f"keys from {tmp_path / '.env'}: VABENCH_DOOR_KEY, VABENCH_DOOR_OTHER" in got.out
    assert "right-key" not in got.out + got.err and "warning" not in got.err

    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    got = capsys.readouterr()
    assert "right-key" not in got.out + got.err
    records = [line for line in (out / "results.jsonl").read_text().splitlines() if line]
    assert len(records) == 2
    for path in out.rglob("*"):  # the key reached no file of the run directory
        if path.is_file():
            assert b"right-key" not in path.read_bytes(), path

    monkeypatch.setenv("VABENCH_DOOR_KEY", "from-the-environment")  # the environment wins
    monkeypatch.delenv("VABENCH_DOOR_OTHER")
    assert main([str(cfg), "--out", str(out), "--dry-run"]) == 0
    assert f"keys from {tmp_path / '.env'}: VABENCH_DOOR_OTHER\n" in capsys.readouterr().out


def test_a_malformed_dotenv_line_is_named_by_number_not_shown(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("VABENCH_DOOR_KEY", raising=False)
    cfg = tmp_path / "keyed.yaml"
    cfg.write_text(KEYED)
    (tmp_path / ".env").write_text("# ok\nsk-secret-without-a-name\n")
    assert main([str(cfg), "--out", str(tmp_path / "out"), "--dry-run"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: {tmp_path / '.env'}: line 2: expected NAME=VALUE (a # starts a comment)"


TINY = """\
name: tiny
models:
  - {name: local, api: openai_chat, base_url: embedded}
embedded_server: {policy: conversation_hash}
tracks: [active, {name: active_none, protocol: active, summaries: none}]
summaries: own
tasks: [grasp_single_cube]
seeds: {verified: 1}
runs: 1
step_budget: 2
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
"""


def test_dry_run_names_the_output_the_summary_modes_and_a_measured_wall_time(tmp_path, capsys):
    """Issue 34: the dry run showed no output directory, no summary mode and no wall time.
    With no earlier sweep of the model kind on this machine it says it has no pace; after one,
    wherever `--out` points, it estimates from that sweep's decisions per second of episode
    time, and the disk from its records; another model kind's pace is never used."""
    runs = tmp_path / "runs"
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY)
    assert main([str(cfg), "--out", str(runs / "first"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"output: {runs / 'first'} (new)" in out
    assert "summaries: active: own, active_none: none" in out
    assert "wall time (embedded conversation_hash at 64x48): no measured pace of this" in out

    assert main([str(cfg), "--out", str(runs / "first"), "--plain", "--no-report"]) == 0
    assert main([str(cfg), "--out", str(runs / "first"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"output: {runs / 'first'}: 2 of 2 episodes already finished" in out
    assert "wall time: nothing left to run" in out

    elsewhere = tmp_path / "elsewhere" / "x"  # not beside the first: the pace is the machine's
    assert main([str(cfg), "--out", str(elsewhere), "--dry-run"]) == 0
    out = capsys.readouterr().out
    records = [json.loads(x) for x in (runs / "first" / "results.jsonl").read_text().splitlines()]
    ends = sorted((r["started_at"], r["started_at"] + r["wall_s"]) for r in records)
    busy = ends[0][1] - ends[0][0] + max(0.0, ends[1][1] - max(ends[1][0], ends[0][1]))
    rate = sum(r["steps_used"] for r in records) / busy
    (line,) = [
        x
        for x in out.splitlines()
        if x.startswith("wall time (embedded conversation_hash at 64x48)")
    ]
    assert f"pace {rate:.2g} decisions a second, 2 episodes in {runs / 'first'}" in line
    assert "expected (2 episodes at the 2.0 decisions an episode measured), at most" in line
    (disk,) = [x for x in out.splitlines() if x.startswith("disk: about")]
    assert "an episode of embedded conversation_hash at 64x48; records.frames: all)" in disk

    assert main([str(SMOKE), "--out", str(runs / "second"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "wall time (embedded reference_servo at 640x480): no measured pace of this" in out


def test_the_pace_leaves_out_the_time_between_a_stop_and_its_resumption():
    from vabench.check.pace import _union_length

    assert _union_length([(100.0, 110.0), (0.0, 10.0), (5.0, 15.0), (6.0, 7.0)]) == 25.0


@pytest.mark.parametrize("dry_run", [[], ["--dry-run"]])
def test_a_missing_config_is_one_line(tmp_path, capsys, dry_run):
    missing = tmp_path / "nowhere.yaml"
    assert main([str(missing), "--out", str(tmp_path / "out"), *dry_run]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0] and "No such file" in err[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "command",
    [
        ["-m", "vabench.llm_pool.serve", "--host", "127.0.0.1", "--port", "{port}"],
        ["-m", "vabench.view", "{run}", "--host", "127.0.0.1", "--port", "{port}"],
    ],
    ids=["llm server", "viewer"],
)
def test_a_port_in_use_is_one_line(tmp_path, command):
    """The server of `python -m vabench.llm_pool.serve` ended in an OSError traceback when
    its port was taken (the viewer already said it in one line)."""
    import socket
    import subprocess
    import sys

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from synthetic_runs import make_run  # a run directory shaped like a sweep's, to serve

    run = make_run(tmp_path / "run", 20).run_dir
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        args = [a.format(port=port, run=run) for a in command]
        done = subprocess.run(
            [sys.executable, *args], capture_output=True, text=True, timeout=120, cwd=ROOT
        )
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert any(f"127.0.0.1:{port}" in line and "cannot listen" in line for line in lines)


def test_a_full_disk_under_the_ledger_is_one_clear_error_and_loses_nothing(tmp_path):
    """A ledger line that cannot be written (ENOSPC, from /dev/full: the kernel's full disk)
    is taken back and stops the sweep with one line (LedgerError, exit 2 in the command),
    instead of an OSError traceback out of an episode task; the episodes recorded before it
    stay."""
    from vabench.agent.records import EpisodeResult
    from vabench.run_layout import RESULTS
    from vabench.sweep.results import Ledger, LedgerError

    def result(seed: int) -> EpisodeResult:
        return EpisodeResult(
            task="grasp_single_cube",
            seed=seed,
            model="m",
            protocol="active",
            run=1,
            status="success",
            success=True,
            stop_reason="success",
            step_budget=2,
            n_checkpoints=1,
        )

    run_dir = tmp_path / "run"
    ledger = Ledger.open(run_dir)
    ledger.add("active", "episodes/a", result(1))
    kept = (run_dir / RESULTS).read_bytes()
    (run_dir / RESULTS).rename(run_dir / "kept.jsonl")
    (run_dir / RESULTS).symlink_to("/dev/full")
    with pytest.raises(LedgerError, match=r"No space left on device.*run the same command"):
        ledger.add("active", "episodes/b", result(2))
    assert len(ledger.records) == 1  # the episode that could not be written is not counted
    (run_dir / RESULTS).unlink()
    (run_dir / "kept.jsonl").rename(run_dir / RESULTS)
    assert (run_dir / RESULTS).read_bytes() == kept
    assert len(Ledger.open(run_dir).records) == 1
