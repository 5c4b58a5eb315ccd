"""The fastest path by default (vabench.sweep.choices): what `auto` picks for physics, renderer
and executor on which machine, said by `--dry-run` with the reasons; the environment worker
processes get on a GPU host; and the processes executor on a CUDA-like host (a fake
CUDA_VISIBLE_DEVICES listing two GPUs) losing nothing."""

from __future__ import annotations

import json
import logging

import pytest

from vabench.config import ExecutorOptions
from vabench.sim_mjx.backends import Choice
from vabench.sweep.__main__ import main
from vabench.sweep.choices import (
    Machine,
    child_environment,
    gpu_for_worker,
    resolve_executor,
    this_machine,
    visible_gpus,
)


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
        ({}, ("0", "1"), "processes", 16),  # several GPUs: workers spread over them
        ({"kind": "processes"}, ("0",), "processes", 16),  # asked for: kept
    ],
)
def test_warp_physics_on_one_gpu_runs_in_one_process(options, gpus, kind, max_tasks):
    warp, c = Choice("mjx", "warp", ""), Choice("c", "-", "")
    choice = resolve_executor(ExecutorOptions(**options), Machine(16, gpus), warp)
    assert (choice.kind, choice.max_tasks) == (kind, max_tasks)
    if kind == "local" and "kind" not in options:
        assert "one GPU" in choice.reason
    # C physics on the same machine: a worker per core, as before
    assert resolve_executor(ExecutorOptions(), Machine(16, gpus), c).kind == "processes"


def test_the_machine_is_read_from_the_environment():
    assert this_machine({"VABENCH_CORES": "12"}).cores == 12
    with pytest.raises(ValueError, match="VABENCH_CORES must be a whole number, got 'many'"):
        this_machine({"VABENCH_CORES": "many"})
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": "0,1"}) == ("0", "1")
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": "2,-1,3"}) == ("2",)  # CUDA stops at -1
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": ""}) == ()
    assert gpu_for_worker(3, ("0", "1")) == "1" and gpu_for_worker(3, ("0",)) is None


def test_workers_never_preallocate_and_keep_jax_off_the_gpu_unless_it_simulates():
    c, warp, jax = Choice("c", "-", ""), Choice("mjx", "warp", ""), Choice("mjx", "jax", "")
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
    # no CUDA GPU here: C MuJoCo and the GL workers, each with the reason
    assert "physics:   C MuJoCo (auto: C MuJoCo (the Warp backend needs" in section
    assert "renderer:  GL worker processes (auto: GL worker processes (" in section
    assert "executor:  local, 4 task batches at once (auto: 2 cores: one process" in section
    assert "in flight: adaptive, at most 256 episodes per process" in section


def test_an_explicit_backend_that_cannot_run_here_is_one_clear_error(tmp_path, capsys):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG.format(extra="simulator: {backend: mjx, impl: warp}"))
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
    summaries = [r.args for r in caplog.records if "cell %s done: %s" in str(r.msg)]
    assert len(summaries) == 2
    for _cell, summary in summaries:
        assert summary["jax"] == "cpu"
        env = summary["environment"]
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
    from vabench.sweep.inflight import BATCHED, InFlight

    cfg = tmp_path / "mjx.yaml"
    cfg.write_text(CONFIG.format(extra="simulator: {backend: mjx, impl: jax}"))
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
    from vabench.sweep.choices import choose

    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(
        CONFIG.format(extra="").replace(
            "{policy: conversation_hash}", "{policy: reference_servo, server_processes: auto}"
        )
        + f"executor: {executor}\n"
    )
    text = "\n".join(choose(load_config(cfg), Machine(cores, ())).lines())
    assert f"server:    {line}" in text
