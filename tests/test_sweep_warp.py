"""The GPU host's path end to end, on Warp's CPU device: what `auto` picks where MuJoCo Warp
runs (Warp physics, Warp's ray-traced images read from the physics batch on the device, one
process stepping every task's batch) through the real sweep, engine, embedded server and
ledger. The unit tests of tests/test_warp_batch.py and tests/test_render_warp.py check the
parts; this checks they hold together as the product runs them: every planned episode recorded
once, none lost to an infrastructure error, the images as asked for. Speed is measured on a GPU
(docs/PERFORMANCE.md, "Whole suite on one GPU"), never here."""

from __future__ import annotations

import io
import json

import pytest
from PIL import Image

from vabench.run_layout import RESULTS
from vabench.sweep.__main__ import main

CONFIG = """\
name: warp-cpu
models:
  - name: local
    api: openai_chat
    base_url: embedded
embedded_server: {policy: random_action}
tracks: [active, passive]
tasks: [grasp_single_cube, place_single_cube]
seeds: {verified: 1}
runs: 1
step_budget: 2
render: {width: 96, height: 72}
executor: {kind: auto}
"""


@pytest.fixture
def warp_on_cpu(monkeypatch):
    """What `auto` sees on a GPU host, with the CPU standing in for the GPU."""
    monkeypatch.setenv("VABENCH_WARP_DEVICE", "cpu")


def test_auto_picks_warp_physics_and_images_in_one_process_where_warp_runs(
    tmp_path, warp_on_cpu, capsys
):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG)
    assert main([str(cfg), "--dry-run"]) == 0
    section = capsys.readouterr().out.split("Runs with:")[1]
    assert "physics:   MuJoCo Warp (auto: MuJoCo Warp on cpu)" in section
    assert "renderer:  MuJoCo Warp's ray tracer" in section
    assert "executor:  local" in section


def test_a_sweep_on_warp_physics_and_warp_images_records_every_episode_once(tmp_path, warp_on_cpu):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG)
    out = tmp_path / "out"
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    records = [json.loads(line) for line in (out / RESULTS).read_text().splitlines()]
    keys = {(r["model"], r["track"], r["task"], r["seed"], r["run"]) for r in records}
    assert len(records) == len(keys) == 4  # 2 tasks x 2 tracks x 1 seed x 1 run
    assert all(r["error"] is None and r["status"] in ("success", "failure") for r in records)
    assert all(r["steps_used"] == 2 for r in records)
    for r in records:
        frames = sorted((out / r["episode_dir"] / "frames").glob("*.jpg"))
        assert frames, r["episode_dir"]
        with Image.open(io.BytesIO(frames[0].read_bytes())) as image:
            assert image.format == "JPEG" and image.size == (96, 72)
    # nothing left to do: the same command resumes to no work
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    assert len((out / RESULTS).read_text().splitlines()) == 4


def test_engine_processes_sharing_the_device_each_take_whole_tasks(
    tmp_path, warp_on_cpu, monkeypatch
):
    """`executor: processes` on Warp physics: whole tasks dealt over the workers
    (`cells.bins`), each worker stepping one batch per task of its chunk (several engine
    processes on one GPU, for CUDA MPS): every planned episode recorded once, each task's
    episodes, every track, in one worker's chunk."""
    from vabench.sweep import process_executor

    planned: list[list[tuple[str, list]]] = []
    real = process_executor.plan_chunks

    def plan_chunks(*args):
        planned.append(real(*args))
        return planned[-1]

    monkeypatch.setattr(process_executor, "plan_chunks", plan_chunks)
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(
        CONFIG.replace("executor: {kind: auto}", "executor: {kind: processes, max_tasks: 2}")
    )
    out = tmp_path / "out"
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    records = [json.loads(line) for line in (out / RESULTS).read_text().splitlines()]
    keys = {(r["model"], r["track"], r["task"], r["seed"], r["run"]) for r in records}
    assert len(records) == len(keys) == 4
    assert all(r["error"] is None and r["status"] in ("success", "failure") for r in records)
    # 4 cells (2 tasks x 2 tracks) in 2 chunks of whole tasks, not one chunk per cell
    (parts,) = planned
    assert sorted(name for name, _ in parts) == ["grasp_single_cube", "place_single_cube"]
    for name, part in parts:
        assert {(k.task, k.track) for k in part} == {(name, "active"), (name, "passive")}
