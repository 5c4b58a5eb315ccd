"""`executor: ray` on a local Ray cluster: the same sweep as the local executor, chunk by chunk
in engine actors, ends with the same records; a rerun runs nothing; a failing chunk is reported
while the others finish; a driver killed mid-sweep takes its engines with it, and the same
command resumes to one record per episode. (A node killed mid-sweep: test_sweep_cluster.py.)

The model is the embedded server's `conversation_hash` policy: each episode's decisions are a
function of its own conversation, so where and in which order episodes run cannot change them.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import ray

from vabench.config import SweepConfigError, load_config
from vabench.config.choices import choose
from vabench.run_layout import WORKER_LOG_PREFIX
from vabench.sweep.__main__ import main
from vabench.sweep.cells import sweep_critical_path, with_critical_path
from vabench.sweep.plan import EpisodeKey, plan
from vabench.sweep.ray_executor import engine_plan, run_ray
from vabench.sweep.ray_plan import engine_environment
from vabench.sweep.results import Ledger, ledger_key

CONFIG = """\
name: ray
models:
  - {{name: local, api: openai_chat, base_url: embedded}}
embedded_server: {{policy: conversation_hash, latency: {{mean_s: 0.02}}, simulate_cache: false}}
tracks: {tracks}
tasks: {tasks}
seeds: {{verified: 2}}
runs: 1
step_budget: 3
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
executor: {executor}
"""
TASKS = "[grasp_single_cube, handover_horizontal_block]"
PLANNED = 2 * 1 * 2 * 2  # tasks x models x tracks x seeds (x 1 run)
# Fields that measure time or host load, not outcome.
TIMING = {"wall_s", "started_at"}


@pytest.fixture(scope="module")
def cluster() -> str:
    """A local Ray cluster for this module (4 CPUs: two engines of 1 + render.workers CPUs);
    its GCS address."""
    try:
        context = ray.init(address="local", num_cpus=4, include_dashboard=False)
    except Exception as err:  # say why, never skip: this module is the ray executor's test
        pytest.fail(f"a local Ray cluster does not start here: {type(err).__name__}: {err}")
    yield context.address_info["gcs_address"]
    ray.shutdown()


def write(path: Path, executor: str, tracks: str = "[active, passive]") -> Path:
    path.write_text(CONFIG.format(tracks=tracks, tasks=TASKS, executor=executor))
    return path


def records(run_dir: Path) -> dict[tuple, dict]:
    out = {}
    for line in (run_dir / "results.jsonl").read_text().splitlines():
        r = json.loads(line)
        key = (r["model"], r["track"], r["task"], r["seed"], r["run"])
        assert key not in out, f"two records for {key}"
        out[key] = {k: v for k, v in r.items() if k not in TIMING}
    return out


def with_sweep_log(terminal: str, out: Path) -> str:
    """What the driver printed and what it logged: the engines' and chunks' lines go to
    RUN_DIR/logs/sweep.log (the terminal shows them with --verbose)."""
    path = out / "logs" / "sweep.log"
    return terminal + (path.read_text() if path.exists() else "")


def ray_sweep(config: Path, out: Path) -> str:
    proc = subprocess.run(
        [sys.executable, "-m", "vabench.sweep", str(config), "--out", str(out), "--plain"]
        + ["--no-report"],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
        timeout=240,
    )
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output[-4000:]
    return output


def test_ray_sweep_equals_the_local_one_and_a_rerun_runs_nothing(cluster, tmp_path):
    local_cfg = write(tmp_path / "local.yaml", "{max_tasks: 2}")
    assert main([str(local_cfg), "--out", str(tmp_path / "local"), "--plain", "--no-report"]) == 0
    ray_cfg = write(tmp_path / "ray.yaml", f"{{kind: ray, address: '{cluster}', max_tasks: 2}}")
    out = tmp_path / "ray"

    log = with_sweep_log(ray_sweep(ray_cfg, out), out)
    assert re.search(
        r"ray: chunks 4/4 done \(0 failed\), 0 running on \d engines \| episodes "
        r"recorded 8/8",
        log,
    ), log[-4000:]
    assert "Pushing file package" in log  # the driver shipped this checkout to the engines
    # each engine's INFO lines in its own log (an engine set up no logging before: a fresh
    # node compiled kernels for minutes in silence)
    engine_logs = sorted((out / "logs").glob(f"{WORKER_LOG_PREFIX}*-*.log"))
    assert engine_logs, sorted(p.name for p in (out / "logs").iterdir())
    lines = "".join(p.read_text() for p in engine_logs)
    assert re.search(r"\w+: physics \d+ calls", lines), lines[-2000:]
    mine, local = records(out), records(tmp_path / "local")
    assert len(mine) == len(local) == PLANNED
    assert mine == local

    ledger = (out / "results.jsonl").read_bytes()
    results = {p: p.stat().st_mtime_ns for p in out.glob("episodes/**/result.json")}
    assert len(results) == PLANNED
    log = with_sweep_log(ray_sweep(ray_cfg, out), out)
    assert "resuming:  8 of 8 already recorded" in log and "nothing to run" in log, log[-4000:]
    assert (out / "results.jsonl").read_bytes() == ledger
    assert {p: p.stat().st_mtime_ns for p in out.glob("episodes/**/result.json")} == results


def test_a_failing_chunk_is_reported_and_the_others_finish(cluster, tmp_path, caplog):
    config = load_config(
        write(tmp_path / "ray.yaml", "{kind: ray, max_tasks: 2}", tracks="[active]"),
        overrides={"tasks": ["grasp_single_cube"], "out": str(tmp_path / "out")},
    )
    run_dir = tmp_path / "out"
    keys = [*plan(config), EpisodeKey("local", "active", "no_such_task", 1, 1)]
    run_dir.mkdir()
    (run_dir / "plan.json").write_text(json.dumps([k.as_id() for k in keys]))
    with caplog.at_level(logging.INFO, logger="vabench.sweep.ray_executor"):
        # joins the module's cluster (already connected)
        got = run_ray(config, keys, run_dir, choose(config))
    assert sorted(got) == sorted(
        (k.model, k.track, k.task, k.seed, k.run) for k in keys if k.task != "no_such_task"
    )
    text = caplog.text
    assert "chunk local/active/no_such_task failed" in text and "no_such_task" in text
    assert "1 chunks failed (1 episodes not run): local/active/no_such_task" in text
    assert ray.is_initialized()  # a connection the caller made is the caller's to close


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_a_killed_driver_takes_its_engines_and_the_rerun_records_each_episode_once(
    cluster, tmp_path
):
    """SIGKILL of the driver mid-sweep: its engines end (Ray ends the actors a driver owns),
    nothing is appended after it, and the same command finishes the plan, one record each."""
    path = tmp_path / "ray.yaml"
    path.write_text(
        CONFIG.format(
            tracks="[active]",
            tasks="[grasp_single_cube]",
            executor=f"{{kind: ray, address: '{cluster}'}}",
        )
        .replace("mean_s: 0.02", "mean_s: 0.4")
        .replace("verified: 2", "verified: 6")
    )
    out = tmp_path / "out"
    log = tmp_path / "driver.log"
    command = [sys.executable, "-m", "vabench.sweep", str(path), "--out", str(out), "--plain"]
    with open(log, "w") as f:
        proc = subprocess.Popen(
            [*command, "--no-report"],
            stdout=f,
            stderr=subprocess.STDOUT,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
    try:
        deadline = time.monotonic() + 180
        while not (out / "results.jsonl").exists() or not (out / "results.jsonl").read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
            time.sleep(0.1)
        said = with_sweep_log(log.read_text(), out)
        engines = [int(p) for p in re.findall(r"engine \d+ started: .*?'pid': (\d+)", said)]
        assert engines
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        at_kill = (out / "results.jsonl").read_bytes()
        deadline = time.monotonic() + 60
        while any(alive(pid) for pid in engines):
            assert time.monotonic() < deadline, "an engine outlived its driver"
            time.sleep(0.2)
        assert (out / "results.jsonl").read_bytes() == at_kill
        assert at_kill.count(b"\n") < 6, "the sweep ended before the kill"
    finally:
        if proc.poll() is None:
            proc.kill()
    ray_sweep(path, out)
    keys = [
        (r["task"], r["seed"])
        for r in map(json.loads, (out / "results.jsonl").read_text().splitlines())
    ]
    assert len(keys) == len(set(keys)) == 6


WRITER = """
import sys
from pathlib import Path
from vabench.run_layout import RESULTS
from vabench.sweep.results import Ledger
run_dir, writer, n = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
ledger = Ledger(run_dir)  # no open(): the test process does the reading
for seed in range(n):
    record = {"model": "m", "track": "active", "task": "t", "seed": seed, "run": writer}
    ledger._append(RESULTS, record | {"pad": "x" * 1_000_000})
"""


def test_appends_from_several_processes_stay_whole_lines_while_others_open(tmp_path):
    """Cells append to one ledger while other cells open it (reading, cutting a torn tail):
    an append in progress must never be taken for a torn line and cut."""
    writers, n = 3, 20
    procs = [
        subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path), str(w), str(n)])
        for w in range(writers)
    ]
    while any(p.poll() is None for p in procs):
        Ledger.open(tmp_path)  # raises on a line that is not a record
    assert all(p.returncode == 0 for p in procs)
    got = Ledger.open(tmp_path).records
    planned = [("m", "active", "t", s, w) for w in range(writers) for s in range(n)]
    assert sorted(got) == sorted(planned)


def test_ray_client_addresses_are_refused_naming_the_field(tmp_path):
    """Ray Client cannot carry the engines' streamed records: say so before anything runs."""
    path = write(tmp_path / "ray.yaml", "{kind: ray, address: 'ray://head:10001'}")
    with pytest.raises(SweepConfigError) as err:
        load_config(path)
    assert "executor.address" in str(err.value) and "address: auto" in str(err.value)


def test_engines_four_per_gpu_under_mps_else_one_per_gpu_or_cpu_share(tmp_path, monkeypatch):
    from vabench.tuning import mps

    monkeypatch.setattr(mps, "control_program", lambda: None)  # no MPS on the driver's node
    config = load_config(write(tmp_path / "ray.yaml", "{kind: ray}"))  # backend c
    cpu_engine = {"num_cpus": 2.0, "num_gpus": 0.0}  # 1 + render.workers
    here = choose(config)
    assert engine_plan(config, here, {"CPU": 16.0, "GPU": 8.0}) == (8, cpu_engine, here)
    auto = config.model_copy(
        update={"simulator": config.simulator.model_copy(update={"backend": "auto"})}
    )
    here = choose(auto)  # what this machine runs (C MuJoCo and GL images without a GPU)
    n, claim, engines = engine_plan(auto, here, {"CPU": 128.0, "GPU": 8.0})
    assert (n, claim) == (8, {"num_cpus": 1.0, "num_gpus": 1.0})  # one a GPU without MPS
    # where MPS can run, four engines share each GPU (on 2 x H200 1.42-1.45x one a GPU)
    monkeypatch.setattr(mps, "control_program", lambda: "/usr/bin/nvidia-cuda-mps-control")
    assert engine_plan(auto, here, {"CPU": 128.0, "GPU": 8.0})[:2] == (
        8 * mps.ENGINES_PER_GPU,
        {"num_cpus": 1.0, "num_gpus": 1.0 / mps.ENGINES_PER_GPU},
    )
    assert engine_plan(auto, here, {"CPU": 5.0})[0] == 2  # CPU engines: MPS changes nothing
    no_mps = auto.model_copy(update={"executor": auto.executor.model_copy(update={"mps": "off"})})
    assert engine_plan(no_mps, here, {"CPU": 128.0, "GPU": 8.0})[:2] == (
        8,
        {"num_cpus": 1.0, "num_gpus": 1.0},
    )
    monkeypatch.setattr(mps, "control_program", lambda: None)
    # what the engines run is decided for their GPUs by the driver, never again by them
    assert (
        engines.physics.is_warp
        and engines.physics.reason == "auto: MuJoCo Warp on each engine's GPU"
    )
    assert engines.renderer.backend == "warp" and engines.in_flight.fixed == 256  # batched
    assert engines.executor == here.executor
    assert engine_plan(auto, here, {"CPU": 5.0}) == (2, cpu_engine, here)  # C MuJoCo engines
    three = auto.model_copy(update={"executor": auto.executor.model_copy(update={"actors": 3})})
    assert engine_plan(three, here, {"CPU": 128.0, "GPU": 8.0})[0] == 3
    # more engines than GPUs: each claims its share of one, so that all of them fit (three on
    # two GPUs: halves), and is told how many share its GPU
    assert engine_plan(three, here, {"CPU": 32.0, "GPU": 2.0})[:2] == (
        3,
        {"num_cpus": 1.0, "num_gpus": 0.5},
    )
    four = auto.model_copy(update={"executor": auto.executor.model_copy(update={"actors": 4})})
    assert engine_plan(four, here, {"CPU": 16.0, "GPU": 1.0})[1]["num_gpus"] == 0.25
    assert engine_environment(four, 4, 4)["VABENCH_GPU_SHARE"] == "4"
    assert "VABENCH_GPU_SHARE" not in engine_environment(four, 4)
    # ... and, unless executor.mps is off, joins its node's CUDA MPS daemon of the sweep's
    assert engine_environment(four, 4, 4, "s1")[mps.NODE_SWEEP] == "s1"
    assert mps.NODE_SWEEP not in engine_environment(four, 4, 1, "s1")  # a GPU each
    off = four.model_copy(update={"executor": four.executor.model_copy(update={"mps": "off"})})
    assert mps.NODE_SWEEP not in engine_environment(off, 4, 4, "s1")
    # a sweep with a critical path ranks its engines' MPS priorities (one normal a GPU)
    assert engine_environment(four, 4, 4, "s1", ranked=True)[mps.NODE_RANKED] == "1"
    assert mps.NODE_RANKED not in engine_environment(four, 4, 4, "s1")
    assert mps.NODE_RANKED not in engine_environment(off, 4, 4, "s1", ranked=True)


def test_batched_engines_get_a_chunk_per_task_across_tracks_and_models():
    """Engines on GPUs step one simulator batch per task of a chunk: chunks of whole tasks
    (every track and model) keep those batches large; nothing is lost or doubled on the way."""
    from vabench.sweep.cells import chunks, pending_cells, task_groups

    keys = [
        EpisodeKey(model, track, task, seed, 1)
        for model in ("a", "b")
        for track in ("active", "passive")
        for task in ("t1", "t2")
        for seed in range(6)
    ]
    done = {("a", "active", "t1", 0, 1)}  # already in the ledger
    cells = pending_cells(keys, done)
    groups = task_groups(cells)
    assert sorted(groups) == [("t1",), ("t2",)]
    assert len(groups[("t1",)]) == 23 and len(groups[("t2",)]) == 24
    parts = chunks(groups, workers=1, cost=lambda task: 1, per_worker=1)
    assert [name for name, _ in parts] == ["t2", "t1"]  # whole tasks, the larger first
    assert {(k.model, k.track) for k in parts[1][1]} == {
        (m, t) for m in ("a", "b") for t in ("active", "passive")
    }
    cut = chunks(groups, workers=2, cost=lambda task: 1, per_worker=2)  # 47 / 4 -> parts of 12
    assert {name for name, _ in cut} == {"t1 part 1/2", "t1 part 2/2", "t2 part 1/2", "t2 part 2/2"}
    flat = [ledger_key(k) for _, part in cut for k in part]
    assert len(flat) == len(set(flat)) == len(keys) - 1


def test_each_engines_time_is_accounted_and_logged(cluster, tmp_path, caplog):
    """The driver's report: every engine's start-up, working and waiting seconds add up to its
    life, its episodes to the sweep's, and the log says the same (no GPU here: no busy share)."""
    config = load_config(
        write(tmp_path / "ray.yaml", "{kind: ray, actors: 2, max_tasks: 1}", tracks="[active]"),
        overrides={"out": str(tmp_path / "out")},
    )
    run_dir = tmp_path / "out"
    keys = plan(config)
    run_dir.mkdir()
    (run_dir / "plan.json").write_text(json.dumps([k.as_id() for k in keys]))
    reports: list[list[dict]] = []
    t0 = time.monotonic()
    with caplog.at_level(logging.INFO, logger="vabench.sweep.ray_executor"):
        got = run_ray(config, keys, run_dir, choose(config), on_engines=reports.append)
    wall = time.monotonic() - t0
    assert len(got) == len(keys) == 4
    [report] = reports
    walls = [json.loads(x) for x in (run_dir / "results.jsonl").read_text().splitlines()]
    assert [r["engine"] for r in report] == [0, 1]
    assert sum(r["episodes"] for r in report) == len(keys)
    for r in report:
        assert not r["died"] and r["host"]
        assert r["start_up_s"] > 0 and r["waiting_s"] >= 0
        # working never exceeds the engine's started life (waiting is not a clamped negative)
        assert r["working_s"] <= r["life_s"] - r["start_up_s"] + 1e-9
        assert r["start_up_s"] + r["working_s"] + r["waiting_s"] == pytest.approx(r["life_s"])
        assert r["life_s"] <= wall
        assert r["gpu_busy"] is None
        # an engine that recorded episodes worked at least as long as one of them took
        if r["episodes"]:
            assert r["working_s"] >= min(rec["wall_s"] for rec in walls)
    lines = [m.getMessage() for m in caplog.records if m.getMessage().startswith("ray: engine")]
    for r in report:
        assert any(
            line.startswith(f"ray: engine {r['engine']} (")
            and f"{r['episodes']} episodes" in line
            and "waiting for work" in line
            for line in lines
        ), lines
    total = [m.getMessage() for m in caplog.records if "ray: engine time" in m.getMessage()]
    assert len(total) == 1 and "over 2 engines" in total[0]


def test_engines_are_told_the_whole_sweeps_critical_path(tmp_path):
    """Each chunk runs in a LocalSweep of its own tasks: the basket's chunks, alone, would
    find nothing to stand out from, and its batches never got the GPU's first priority."""
    choices = choose(load_config(write(tmp_path / "ray.yaml", "{kind: ray}")))
    budgets = {"put_everything_in_basket": 250, "place_cube_on_cube": 200, "a": 50, "b": 50}
    told = with_critical_path(choices, budgets)
    assert told.executor.critical_path == ("put_everything_in_basket",)
    assert choices.executor.critical_path is None  # the command's choices are left alone
    # what an engine's chunk then runs with: the basket's alone, and a chunk of others
    path = told.executor.critical_path
    assert sweep_critical_path(path, {"put_everything_in_basket": 250}) == {
        "put_everything_in_basket"
    }
    assert sweep_critical_path(path, {"place_cube_on_cube": 200, "a": 50}) == set()
    assert with_critical_path(choices, {"a": 50, "b": 50}).executor.critical_path == ()


def test_a_spend_cap_holds_across_ray_engines(cluster, tmp_path):
    """Two tasks on two engines, one cap: every call's upper bound is reserved on the driver's
    limit board (each engine counting alone would spend up to it), so together they stop at
    the cap, in one line, each recorded episode once."""
    from tests.test_sweep_cost import BODY, ledger, paid
    from vabench.report.spend import bill

    two_tasks = BODY.replace("[grasp_single_cube]", "[grasp_single_cube, grasp_single_pen]")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        f"name: cost\nmodels:\n{paid('paid', 5)}{two_tasks}"
        f"executor: {{kind: ray, address: '{cluster}', max_tasks: 2}}\n"
    )
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "vabench.sweep", str(cfg), "--out", str(out), "--plain"]
        + ["--no-report", "--no-check"],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
        timeout=240,
    )
    assert proc.returncode == 2, (proc.stdout + proc.stderr)[-4000:]
    assert "stopped: limits.max_cost_usd of model 'paid' ($5) reached at $" in proc.stderr
    assert 0 < bill(out).total("paid") <= 5
    keys = [(r["task"], r["seed"]) for r in ledger(out)]
    assert len(keys) == len(set(keys))
