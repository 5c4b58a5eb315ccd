"""The fastest path by default (vabench.config.choices): what `auto` picks for physics, renderer
and executor on which machine, said by `--dry-run` with the reasons; the environment worker
processes get on a GPU host; and the processes executor on a CUDA-like host (a fake
CUDA_VISIBLE_DEVICES listing two GPUs) losing nothing."""

from __future__ import annotations

import json
import logging
import sys
from dataclasses import replace

import pytest

from vabench.config import ExecutorOptions
from vabench.config.choices import (
    Choices,
    Machine,
    choose,
    resolve_executor,
    this_machine,
    visible_gpus,
)
from vabench.sim_mjx.backends import Choice, Physics
from vabench.sweep.__main__ import main
from vabench.tuning.engine_env import child_environment, gpu_for_worker


@pytest.mark.parametrize(
    ("options", "cores", "kind", "max_tasks"),
    [
        ({}, 2, "local", 4),
        ({}, 3, "local", 4),
        ({}, 4, "processes", 4),
        ({}, 16, "processes", 16),
        ({"max_tasks": 6}, 16, "processes", 6),
        ({"kind": "local"}, 16, "local", 4),
        ({"kind": "processes"}, 8, "processes", 8),
        ({"kind": "ray"}, 8, "ray", 16),  # chunks at once per engine actor
    ],
)
def test_the_executor_is_sized_from_the_cores(options, cores, kind, max_tasks):
    choice = resolve_executor(ExecutorOptions(**options), Machine(cores, ()))
    assert (choice.kind, choice.max_tasks) == (kind, max_tasks)
    assert choice.reason.startswith("auto: ") == ("kind" not in options)


@pytest.mark.parametrize(
    ("options", "gpus", "kind", "max_tasks"),
    [
        ({}, ("0",), "local", 64),  # one process steps every task batch on the GPU
        ({}, (), "local", 64),  # Warp on the CPU (tests): one process as well
        ({"max_tasks": 8}, ("0",), "local", 8),
        ({}, ("0", "1"), "processes", 2),  # several GPUs: one engine process per GPU
        ({}, ("0", "1", "2", "3"), "processes", 4),
        ({"max_tasks": 8}, ("0", "1"), "processes", 8),  # asked for: kept
        ({"kind": "processes"}, ("0",), "processes", 16),  # asked for: kept
    ],
)
def test_warp_physics_on_one_gpu_runs_in_one_process(options, gpus, kind, max_tasks):
    warp, c = Choice(Physics.WARP, ""), Choice(Physics.C, "")
    choice = resolve_executor(ExecutorOptions(**options), Machine(16, gpus), warp)
    assert (choice.kind, choice.max_tasks) == (kind, max_tasks)
    if kind == "local" and "kind" not in options:
        assert "one GPU" in choice.reason
    if kind == "processes" and not options:
        assert f"one engine process per GPU ({16 // len(gpus)} cores each)" in choice.reason
    # C physics on the same machine: a worker per core, as before
    assert resolve_executor(ExecutorOptions(), Machine(16, gpus), c).kind == "processes"


@pytest.mark.parametrize(
    ("options", "gpus", "kind", "max_tasks", "per_gpu"),
    [
        ({}, ("0",), "processes", 4, 4),  # 4 engine processes share the GPU under MPS
        ({}, ("0", "1"), "processes", 8, 4),
        ({"max_tasks": 2}, ("0",), "processes", 2, 2),
        ({"mps": "off"}, ("0",), "local", 64, 1),  # without MPS: as before
        ({"mps": "off"}, ("0", "1"), "processes", 2, 1),
        ({"kind": "processes", "max_tasks": 8}, ("0",), "processes", 8, 8),  # asked for
        ({"kind": "processes"}, ("0",), "processes", 4, 4),  # engines, not one per core
        ({"kind": "processes", "max_tasks": 2}, ("0", "1"), "processes", 2, 1),  # one per GPU
        ({"kind": "local"}, ("0",), "local", 4, 1),
    ],
)
def test_engine_processes_share_a_gpu_under_mps_where_it_is_installed(
    options, gpus, kind, max_tasks, per_gpu
):
    """Engine processes under CUDA MPS keep a GPU busier than one process (docs/PERFORMANCE.md,
    "Engine processes on one GPU"): `auto` runs them where NVIDIA's MPS control program is
    installed, and says so; `mps: off` keeps the one-process layout."""
    warp, c = Choice(Physics.WARP, ""), Choice(Physics.C, "")
    machine = Machine(16, gpus, mps=True)
    choice = resolve_executor(ExecutorOptions(**options), machine, warp)
    assert (choice.kind, choice.max_tasks, choice.per_gpu) == (kind, max_tasks, per_gpu)
    assert choice.mps == (per_gpu > 1)
    if choice.mps:
        assert f"{per_gpu} per GPU under CUDA MPS" in choice.label
    if not options:
        assert "under a CUDA MPS daemon of the sweep's own" in choice.reason
        assert f"({16 // max_tasks} cores each)" in choice.reason
    assert not resolve_executor(ExecutorOptions(**options), machine, c).mps
    assert not resolve_executor(ExecutorOptions(**options), Machine(16, gpus), warp).mps


def test_the_episodes_in_flight_on_a_gpu_are_shared_by_its_engine_processes(monkeypatch):
    """`executor.max_episodes` (1,024 in configs/all.yaml) stays the GPU's: 4 engine processes
    sharing it keep 256 each in flight, the layout measured."""
    from vabench.config import choices as choices_module
    from vabench.config import load_config

    monkeypatch.setattr(choices_module, "resolve", lambda *a, **k: Choice(Physics.WARP, ""))
    config = load_config("configs/all.yaml")
    picked = choose(config, Machine(16, ("0",), mps=True))
    assert picked.executor.per_gpu == 4 and picked.in_flight.ceiling == 256
    assert "256 episodes per process" in picked.in_flight.describe()
    alone = choose(config, Machine(16, ("0",)))
    assert alone.executor.kind == "local" and alone.in_flight.ceiling == 1024


def test_the_machine_is_read_from_the_environment():
    assert this_machine({"VABENCH_CORES": "12"}).cores == 12
    with pytest.raises(ValueError, match="VABENCH_CORES must be a whole number >= 1, got 'many'"):
        this_machine({"VABENCH_CORES": "many"})
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": "0,1"}) == ("0", "1")
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": "2,-1,3"}) == ("2",)  # CUDA stops at -1
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": ""}) == ()
    assert gpu_for_worker(3, ("0", "1")) == "1" and gpu_for_worker(3, ("0",)) is None


def test_workers_never_preallocate_and_keep_jax_off_the_gpu_unless_it_simulates():
    c, warp, jax = Choice(Physics.C, ""), Choice(Physics.WARP, ""), Choice(Physics.MJX_JAX, "")
    cpu_jax = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false", "JAX_PLATFORMS": "cpu"}
    assert child_environment(c, {}) == cpu_jax
    assert child_environment(warp, {}) == cpu_jax  # Warp's physics uses JAX on the host only
    assert child_environment(jax, {}) == {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    assert child_environment(c, {"JAX_PLATFORMS": "cuda"}) == {  # the user's choice stands
        "XLA_PYTHON_CLIENT_PREALLOCATE": "false"
    }


CONFIG = """\
name: choices
models:
  - {{name: local, api: openai_chat, base_url: embedded}}
embedded_server: {{policy: conversation_hash}}
tracks: [active]
summaries: none
tasks: [grasp_single_cube, handover_horizontal_block]
seeds: {{verified: 2}}
runs: 1
step_budget: 2
render: {{width: 64, height: 48, workers: 1}}
{extra}
"""


def test_dry_run_says_what_was_picked_and_why(tmp_path, capsys):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG.format(extra=""))
    assert main([str(cfg), "--dry-run"]) == 0
    text = capsys.readouterr().out
    section = text[text.index("Runs with:") :]
    assert "machine:   2 cores (VABENCH_CORES)" in section
    # no CUDA GPU here: C MuJoCo and the GL workers, each with the reason, the choice named
    # once (`C MuJoCo (auto: C MuJoCo (the Warp backend needs ... (pip install ...)))`
    # nested parentheses three deep)
    assert "physics:   C MuJoCo (auto: the Warp backend needs" in section
    assert "renderer:  GL worker processes (auto: the Warp renderer needs" in section
    for line in section.splitlines()[1:]:
        depth = deepest = 0
        for ch in line:
            depth += {"(": 1, ")": -1}.get(ch, 0)
            deepest = max(deepest, depth)
        assert deepest <= 2 and depth == 0, line
    assert "executor:  local, 4 task batches at once (auto: 2 cores: one process" in section
    assert "in flight: adaptive, at most 256 episodes per process" in section


def test_an_explicit_backend_that_cannot_run_here_is_one_clear_error(tmp_path, capsys):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG.format(extra="simulator: {backend: warp}"))
    assert main([str(cfg), "--dry-run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the Warp backend needs" in err[0] and str(cfg) in err[0]


def test_auto_runs_worker_processes_on_a_cuda_like_host_and_loses_nothing(
    tmp_path, monkeypatch, caplog
):
    """A host with 4 cores and two (fake) GPUs: `executor: auto` runs worker processes, each
    with JAX kept off the GPU (no CUDA physics here), no preallocation, one of the GPUs and its
    share of the cores; every planned episode is recorded exactly once."""
    monkeypatch.setenv("VABENCH_CORES", "4")
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0,1")
    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG.format(extra=""))
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO):
        assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    assert "executor:  processes, 4 cells at once (auto: 4 cores" in caplog.text
    assert "one of GPUs 0,1 each" in caplog.text
    started = [r.args for r in caplog.records if "engine %d started: %s" in str(r.msg)]
    assert len(started) == 2
    for _engine, info in started:
        assert info["jax"] == "cpu"
        env = info["environment"]
        assert env["JAX_PLATFORMS"] == "cpu" and env["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
        assert env["CUDA_VISIBLE_DEVICES"] in ("0", "1")
        assert env["VABENCH_CORES"] == "2"  # 4 cores, 2 workers: each sizes its pools to 2
    lines = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    keys = {(r["task"], r["seed"]) for r in lines}
    assert len(lines) == len(keys) == 4
    assert all(r["status"] in ("success", "failure") for r in lines)


def test_batched_physics_fills_its_batch_instead_of_adapting(tmp_path, capsys):
    """MJX (and MuJoCo Warp) step every slot of a batch for the price of one: `in_flight: auto`
    holds the ceiling there and says why; C MuJoCo adapts."""
    from vabench.tuning.inflight import BATCHED, InFlight

    cfg = tmp_path / "mjx.yaml"
    cfg.write_text(CONFIG.format(extra="simulator: {backend: mjx}"))
    assert main([str(cfg), "--dry-run"]) == 0
    assert f"in flight: 256 episodes per process at most ({BATCHED})" in capsys.readouterr().out
    gate = InFlight(256, 256, why=BATCHED)
    assert gate.limit == 256 and gate.reason == BATCHED
    gate.observe("k", 10.0)  # slow decisions never shrink it
    assert gate.limit == 256


def test_policy_workers_take_half_the_cores_from_four_on(monkeypatch):
    from vabench.llm_pool.server import ServerConfig, policy_workers

    for cores, expected in (("2", 0), ("3", 0), ("4", 2), ("16", 8)):
        monkeypatch.setenv("VABENCH_CORES", cores)
        assert policy_workers("auto") == expected
    assert policy_workers(3) == 3
    assert ServerConfig(policy_processes="auto").policy_processes == "auto"
    with pytest.raises(ValueError, match="policy_processes"):
        ServerConfig(policy_processes="many")


@pytest.mark.parametrize(
    ("cores", "executor", "line"),
    [
        (2, "{kind: local}", "embedded, in the engine's process (the sweep's process has 2 cores)"),
        (16, "{kind: local}", "embedded, 8 processes on one port, each computing its replies"),
        (16, "{kind: processes}", "embedded, in the engine's process (each worker has 1 core)"),
        (
            16,
            "{kind: processes, max_tasks: 2}",
            "embedded, 4 processes on one port, each computing its replies (each worker has 8",
        ),
    ],
)
def test_the_embedded_server_is_sized_to_the_engine_process_share(tmp_path, cores, executor, line):
    """configs/all.yaml's server: a sweep process sizes its embedded server to its cores; a
    worker process of `processes` to its share (16 workers on 16 cores serve in-process)."""
    from vabench.config import load_config
    from vabench.config.choices import choose

    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(
        CONFIG.format(extra="").replace(
            "{policy: conversation_hash}", "{policy: reference_servo, server_processes: auto}"
        )
        + f"executor: {executor}\n"
    )
    text = "\n".join(choose(load_config(cfg), Machine(cores, ())).lines())
    assert f"server:    {line}" in text


def count_resolutions(monkeypatch) -> dict[str, int]:
    """Count the calls of `resolve` (physics) and `resolve_renderer`, under every name a loaded
    vabench module holds them by (a module that imports one later gets the counted one)."""
    from vabench.render import backends as render
    from vabench.sim_mjx import backends as physics

    counts = {"physics": 0, "renderer": 0}
    for key, original in (("physics", physics.resolve), ("renderer", render.resolve_renderer)):

        def counted(*args, _key=key, _original=original, **kwargs):
            counts[_key] += 1
            return _original(*args, **kwargs)

        for name, module in list(sys.modules.items()):
            if name.startswith("vabench"):
                for attr, value in list(vars(module).items()):
                    if value is original:
                        monkeypatch.setattr(module, attr, counted)
    return counts


def test_one_resolution_per_command_and_the_local_executor_runs_what_the_dry_run_says(
    tmp_path, monkeypatch, capsys
):
    """`--dry-run` and the run are one `choose` each; the sweep it runs receives that very
    `Choices` (physics, renderer, task batches at once, the in-flight gate) and decides none of
    it again: a rule it received that the config alone would not give (3 episodes in flight
    where the config says auto) is the rule its gate holds."""
    import vabench.sweep.__main__ as command
    from vabench.sweep import chunk_engine
    from vabench.sweep.runner import LocalSweep
    from vabench.tuning.inflight import InFlightRule

    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG.format(extra="executor: {kind: local}"))
    counts = count_resolutions(monkeypatch)
    assert main([str(cfg), "--dry-run"]) == 0
    dry_run = capsys.readouterr().out.split("Runs with:\n")[1].splitlines()[:5]
    assert counts == {"physics": 1, "renderer": 1}

    chosen: list[Choices] = []
    sweeps: list[LocalSweep] = []

    def choose_three(config, **kwargs):
        chosen.append(replace(choose(config, **kwargs), in_flight=InFlightRule(256, 3)))
        return chosen[-1]

    class Recorded(LocalSweep):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            sweeps.append(self)

    monkeypatch.setattr(command, "choose", choose_three)
    monkeypatch.setattr(chunk_engine, "LocalSweep", Recorded)  # the in-process engine's
    assert main([str(cfg), "--out", str(tmp_path / "out"), "--plain", "--no-report"]) == 0
    assert counts == {"physics": 2, "renderer": 2}  # the run's own choose, nothing after it
    ((choices,), (sweep,)) = chosen, sweeps
    assert [f"  {line}" for line in choices.lines()[:4]] == dry_run[:4]
    assert sweep.choices is choices and sweep.physics is choices.physics
    assert sweep.gate is not None
    assert (sweep.gate.limit, sweep.gate.reason) == (3, "executor.in_flight = 3")


def test_worker_processes_run_on_the_choices_they_are_sent(tmp_path, monkeypatch, caplog):
    """The processes executor resolves nothing (the command did) and its workers run on the
    `Choices` they are sent: the in-flight rule they report is the one sent, not one derived
    from the config again."""
    from vabench.config import load_config
    from vabench.sweep.plan import plan
    from vabench.sweep.process_executor import run_processes
    from vabench.tuning.inflight import InFlightRule

    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG.format(extra="executor: {kind: processes, max_tasks: 1}"))
    run_dir = tmp_path / "out"
    config = load_config(cfg, overrides={"tasks": ["grasp_single_cube"], "out": str(run_dir)})
    keys = plan(config)
    run_dir.mkdir()
    (run_dir / "plan.json").write_text(json.dumps([k.as_id() for k in keys]))
    sent = replace(choose(config), in_flight=InFlightRule(256, 3))
    counts = count_resolutions(monkeypatch)
    with caplog.at_level(logging.INFO, logger="vabench.sweep.process_executor"):
        assert len(run_processes(config, keys, run_dir, sent)) == len(keys) == 2
    assert counts == {"physics": 0, "renderer": 0}
    ((_chunk, _engine, summary),) = [
        r.args for r in caplog.records if "chunk %s done on %s: %s" in str(r.msg)
    ]
    assert summary["in_flight"] == "executor.in_flight = 3"
    assert summary["physics"] == sent.physics.label
