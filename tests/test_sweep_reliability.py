"""What the sweep promises across invocations (docs/RELIABILITY.md), each through the command:

- a run directory belongs to one plan: resuming it with a config whose plan differs is refused,
  naming the differing fields, before anything runs;
- an endpoint that refuses the sweep's requests (a wrong key, an unknown model) stops the sweep
  within its first calls, naming the model and the key's variable; nothing is recorded for the
  episodes it touched, and the same command runs them once the endpoint is fixed;
- a duplicate ledger record (two writers raced) is reported and collapsed on resume, not fatal.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vabench.run_layout import RESULTS
from vabench.sweep.__main__ import main

CONFIG = """\
name: reliability
models:
  - name: local
    api: {api}
    base_url: embedded
    retry: {{max_attempts: 2, backoff_base_s: 0.01, backoff_max_s: 0.02}}
embedded_server: {server}
tracks: [active]
tasks: [grasp_single_cube]
seeds: {{verified: 2}}
runs: 1
step_budget: {budget}
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
"""


def write(
    path: Path,
    *,
    server: str = "{policy: conversation_hash}",
    budget: int = 2,
    api: str = "openai_chat",
) -> Path:
    path.write_text(CONFIG.format(server=server, budget=budget, api=api))
    return path


def ledger_lines(run_dir: Path) -> list[dict]:
    path = run_dir / RESULTS
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def test_resuming_with_another_plan_is_refused_naming_the_fields(tmp_path, capsys):
    out = tmp_path / "out"
    cfg = write(tmp_path / "a.yaml", budget=2)
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    before = (out / RESULTS).read_bytes()
    assert len(ledger_lines(out)) == 2
    capsys.readouterr()

    changed = write(tmp_path / "b.yaml", budget=3)
    assert main([str(changed), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "step_budget: 2 -> 3" in err and "--out" in err
    assert (out / RESULTS).read_bytes() == before  # nothing ran, nothing was written

    # what does not decide the plan (retries, render workers) may change
    same = tmp_path / "c.yaml"
    same.write_text(cfg.read_text().replace("max_attempts: 2", "max_attempts: 3"))
    assert main([str(same), "--out", str(out), "--plain", "--no-report"]) == 0
    assert (out / RESULTS).read_bytes() == before


PROCESSES = """\
name: orphans
models:
  - {name: local, api: openai_chat, base_url: embedded}
embedded_server: {policy: conversation_hash, latency: {mean_s: 0.25}}
tracks: [active]
summaries: none
tasks: [grasp_single_cube, handover_horizontal_block]
seeds: {verified: 3}
runs: 1
step_budget: 5
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
executor: {kind: processes, max_tasks: 2, slots_per_task: 1}
"""


def descendants(pid: int) -> set[int]:
    """Every live process below `pid` (from /proc)."""
    parents: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents[int(stat.parent.name)] = int(fields[1])
    out: set[int] = set()
    frontier = {pid}
    while frontier:
        frontier = {p for p, pp in parents.items() if pp in frontier} - out
        out |= frontier
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _processes_sweep_mid_episode(tmp_path: Path, *extra: str):
    """Start the PROCESSES sweep as a subprocess (own session) and return (config, run
    directory, process) once a cell worker is in the middle of an episode (a reply logged)."""
    cfg = tmp_path / "processes.yaml"
    cfg.write_text(PROCESSES)
    out = tmp_path / "out"
    command = [sys.executable, "-m", "vabench.sweep", str(cfg), "--out", str(out), "--plain"]
    proc = subprocess.Popen(
        [*command, *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
        start_new_session=True,
    )
    deadline = time.monotonic() + 240
    while not any('"type": "reply"' in p.read_text() for p in out.glob("episodes/**/events.jsonl")):
        if proc.poll() is not None or time.monotonic() > deadline:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
            raise AssertionError(f"no episode started in time: {proc.communicate()[0][-3000:]}")
        time.sleep(0.05)
    return cfg, out, proc


def test_processes_workers_die_with_a_killed_parent_and_never_write_the_ledger(tmp_path):
    """SIGKILL of the sweep's main process alone (not its group): its cell workers must not
    go on calling the model and appending records (defect A); the next invocation finishes
    the plan with exactly one record per episode."""
    cfg, out, proc = _processes_sweep_mid_episode(tmp_path)
    workers: set[int] = set()
    try:
        workers = descendants(proc.pid)
        assert workers
        os.kill(proc.pid, signal.SIGKILL)  # the main process only
        proc.wait()
        ledger_at_kill = (out / RESULTS).read_bytes() if (out / RESULTS).exists() else b""
        deadline = time.monotonic() + 120
        while any(alive(p) for p in workers):
            assert time.monotonic() < deadline, "the workers outlived their parent"
            time.sleep(0.1)
        ledger_after = (out / RESULTS).read_bytes() if (out / RESULTS).exists() else b""
        assert ledger_after == ledger_at_kill, "a worker wrote the ledger after its parent died"
    finally:
        for pid in [proc.pid, *workers]:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
        proc.stdout.close()

    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    keys = [(r["task"], r["seed"]) for r in ledger_lines(out)]
    assert len(keys) == len(set(keys)) == 6


def test_a_dead_worker_is_replaced_and_its_chunks_rerun(tmp_path):
    """An engine process killed mid-episode (a native crash, the out-of-memory killer) costs
    only its chunk's unfinished episodes: another engine runs them and the sweep finishes the
    plan in the same invocation, one record per episode."""
    _, out, proc = _processes_sweep_mid_episode(tmp_path, "--no-report")
    try:
        workers = [
            pid
            for pid in descendants(proc.pid)
            if _parent(pid) == proc.pid and b"spawn_main" in _cmdline(pid)
        ]
        assert workers
        os.kill(workers[0], signal.SIGKILL)
        text, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, text[-3000:]
    assert "a worker process died" in text and "Traceback" not in text
    keys = [(r["task"], r["seed"]) for r in ledger_lines(out)]
    assert len(keys) == len(set(keys)) == 6


def _parent(pid: int) -> int:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except OSError:
        return -1


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


REFUSING = """\
name: refused
models:
  - {{name: local, api: anthropic, base_url: embedded, api_key_env: VABENCH_TEST_KEY}}
embedded_server: {{policy: conversation_hash, api_key: right-key}}
tracks: [active]
summaries: {summaries}
tasks: [grasp_single_cube]
seeds: {{verified: 3}}
runs: 1
step_budget: 2
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
executor: {{slots_per_task: 1}}
"""


def logged_requests(run_dir: Path) -> int:
    """Model requests logged anywhere under the run directory (episodes, learning sessions,
    their set-aside attempts)."""
    return sum(
        p.read_text().count('"type": "endpoint_refused"') + p.read_text().count('"type": "reply"')
        for p in run_dir.rglob("events.jsonl")
    )


@pytest.mark.parametrize("summaries", ["none", "own"])
def test_a_wrong_key_stops_the_sweep_and_the_fixed_run_does_every_episode(
    tmp_path, capsys, monkeypatch, summaries
):
    """Defect D: a 401 used to be recorded as a final error of every episode, and running the
    command again after fixing the key did nothing. Now the first refused call stops the sweep
    (the learning session's or the first episode's), naming the model and the variable;
    nothing is recorded; the same command with the right key runs every episode."""
    cfg = tmp_path / "refused.yaml"
    cfg.write_text(REFUSING.format(summaries=summaries))
    out = tmp_path / "out"
    monkeypatch.setenv("VABENCH_TEST_KEY", "wrong-key")
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "model 'local'" in err and "VABENCH_TEST_KEY" in err and "401" in err
    assert ledger_lines(out) == []
    assert logged_requests(out) == 1  # one call refused, no other was made
    assert not list(out.glob("summaries/local/*.json"))  # no refusal stored as a summary
    assert not list(out.glob("episodes/**/result.json"))

    monkeypatch.setenv("VABENCH_TEST_KEY", "right-key")
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    records = ledger_lines(out)
    assert sorted(r["seed"] for r in records) == sorted({r["seed"] for r in records})
    assert len(records) == 3 and all(r["status"] in ("success", "failure") for r in records)
    for path in out.rglob("*"):  # neither key reached the run directory
        if path.is_file():
            data = path.read_bytes()
            assert b"right-key" not in data and b"wrong-key" not in data, path


def test_nothing_answering_at_base_url_stops_the_sweep_and_the_run_with_a_server_does_all(
    tmp_path, capsys
):
    """Issue 34 (2026-11-26): a sweep against nothing on 127.0.0.1:8000 did three retry rounds,
    then recorded `infrastructure_error ... ClientConnectorError` for every episode. An
    endpoint that never answered now stops the sweep at its first call like a wrong key,
    naming the model and its base_url; nothing is recorded; once a server listens there
    (a real process), the same command runs every episode."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    base_url = f"http://127.0.0.1:{port}/v1"
    cfg = tmp_path / "unreachable.yaml"
    cfg.write_text(
        write(tmp_path / "x.yaml")
        .read_text()
        .replace("base_url: embedded", f"base_url: {base_url}")
        .replace("embedded_server: {policy: conversation_hash}\n", "")
    )
    out = tmp_path / "out"
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "model 'local'" in err and base_url in err and "server is running" in err
    assert ledger_lines(out) == [] and not (out / "infrastructure.jsonl").exists()
    assert not list(out.glob("episodes/**/result.json"))
    assert not list(out.glob("summaries/local/*.json"))

    server = subprocess.Popen(
        [sys.executable, "-m", "vabench.llm_pool.serve", "--port", str(port)]
        + ["--policy", "conversation_hash"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert server.stdout is not None and "llm server on" in server.stdout.readline()
        assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    finally:
        server.terminate()
        server.wait(timeout=30)
    records = ledger_lines(out)
    assert len(records) == 2 and all(r["status"] in ("success", "failure") for r in records)


def test_a_failed_gpu_stops_the_sweep_and_the_next_run_does_every_episode(
    tmp_path, capsys, monkeypatch
):
    """On an H100 (2026-11-26) an illegal memory access killed the process's CUDA context 13 s
    into a sweep; every later call on the device failed, and each of the 2,160 episodes was
    recorded as a harness error within 26 s, none of them run again by a resume. A failed
    device (`DeviceFailure`, raised by the Warp backends once the context reports its sticky
    error) now stops the sweep like a refusing endpoint: nothing recorded for the episodes it
    interrupted, the reason printed, and the same command runs every episode. The C backend
    stands in for the GPU here: its step fails from the second action on, as a dead context's
    calls do."""
    from vabench.sim_mjx.cpu import CpuBatch
    from vabench.sim_mjx.interface import DeviceFailure

    cfg = write(tmp_path / "gpu.yaml", budget=3)
    out = tmp_path / "out"
    real = CpuBatch._execute
    calls = {"n": 0}

    def failing(self, rows):
        calls["n"] += 1
        if calls["n"] >= 2:
            raise DeviceFailure("the CUDA context of cuda:0 failed (CUDA error 700: ...)")
        return real(self, rows)

    monkeypatch.setattr(CpuBatch, "_execute", failing)
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "CUDA context of cuda:0 failed" in err and "same command" in err
    assert ledger_lines(out) == []
    assert not list(out.glob("episodes/**/result.json"))

    monkeypatch.setattr(CpuBatch, "_execute", real)
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    records = ledger_lines(out)
    assert len(records) == 2 and all(r["status"] in ("success", "failure") for r in records)


@pytest.mark.parametrize("where", ["action", "batch"])
def test_any_error_after_a_gpu_context_failed_stops_the_sweep_unrecorded(
    tmp_path, capsys, monkeypatch, where
):
    """After a sticky CUDA error every later call fails wherever it is made, as whatever
    error that call raises: on an H100 with 8 engine processes under MPS (2026-11-27) 136
    episodes were recorded as harness errors ("Failed to allocate 4 bytes on device 'cuda:0'",
    "Failed to load CUDA module 'mujoco_warp._src.render_util'") raised outside the calls
    that check the context. Every episode error (and a task's batch that cannot be built) now
    asks the devices' registered checks first (`interface.device_failure`). The C backend
    stands in for the GPU; the check is registered as `warp.device.device_lock` does."""
    from vabench.sim_mjx import interface
    from vabench.sim_mjx.cpu import CpuBatch

    monkeypatch.setattr(interface, "_CONTEXT_CHECKS", {})
    failed = {"now": False}
    interface.watch_device(
        "cuda:0",
        lambda: (
            "the CUDA context of cuda:0 failed (CUDA error 700: CUDA_ERROR_ILLEGAL_ADDRESS)"
            if failed["now"]
            else None
        ),
    )
    cfg = write(tmp_path / "gpu.yaml", budget=3)
    out = tmp_path / "out"
    if where == "action":
        real = CpuBatch._execute

        def failing(self, rows):
            failed["now"] = True
            raise RuntimeError("Failed to allocate 4 bytes on device 'cuda:0'")

        monkeypatch.setattr(CpuBatch, "_execute", failing)
    else:
        real = CpuBatch.__init__

        def failing(self, *args, **kwargs):
            failed["now"] = True
            raise RuntimeError("Failed to load CUDA module 'mujoco_warp._src.render_util'")

        monkeypatch.setattr(CpuBatch, "__init__", failing)
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "CUDA error 700" in err and "first error here: RuntimeError: Failed to" in err
    assert "same command" in err
    assert ledger_lines(out) == []
    assert not list(out.glob("episodes/**/result.json"))

    failed["now"] = False  # a new process: a new context
    monkeypatch.setattr(CpuBatch, "_execute" if where == "action" else "__init__", real)
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    records = ledger_lines(out)
    assert len(records) == 2 and all(r["status"] in ("success", "failure") for r in records)


def test_a_cuda_device_lock_registers_its_context_check(monkeypatch):
    """Whoever queues work on a CUDA device takes its lock (`warp.device.device_lock`), which
    registers the device's context check once; a CPU device has none. A device this process
    does not have (no CUDA here, or a higher index on a GPU host) reports no failure, so an
    ordinary error stays the episode's."""
    from vabench.sim_mjx import interface
    from vabench.sim_mjx.warp import device

    monkeypatch.setattr(interface, "_CONTEXT_CHECKS", {})
    monkeypatch.setattr(device, "_DEVICE_LOCKS", {})
    device.device_lock("cpu")
    assert interface._CONTEXT_CHECKS == {}
    device.device_lock("cuda:63")
    device.device_lock("cuda:63")
    assert list(interface._CONTEXT_CHECKS) == ["cuda:63"]
    assert interface.device_failure(RuntimeError("an ordinary bug")) is None
    failure = interface.DeviceFailure("dead")
    assert interface.device_failure(failure) is failure


GPU_FAILS_ONCE = """\
import os
import sys

if "spawn_main" in " ".join(getattr(sys, "orig_argv", [])):  # the sweep's worker processes
    from vabench.sim_mjx import cpu, interface

    flags = os.environ["VABENCH_TEST_FLAGS"]
    mine = os.path.join(flags, f"failed-{os.getpid()}")
    interface.watch_device(
        "cuda:0",
        lambda: "the CUDA context of cuda:0 failed (CUDA error 700: CUDA_ERROR_ILLEGAL_ADDRESS)"
        if os.path.exists(mine)
        else None,
    )
    real = cpu.CpuBatch._execute

    def failing(self, rows):
        if os.path.exists(mine):  # a dead context fails every later call of its process
            raise RuntimeError("Failed to allocate 4 bytes on device 'cuda:0'")
        try:  # the first action of the whole sweep, in whichever worker makes it
            os.close(os.open(os.path.join(flags, "claimed"), os.O_CREAT | os.O_EXCL))
        except FileExistsError:
            return real(self, rows)
        open(mine, "w").close()
        raise RuntimeError("Failed to allocate 4 bytes on device 'cuda:0'")

    cpu.CpuBatch._execute = failing
"""


@pytest.mark.parametrize("workers", [2, 1])
def test_a_worker_whose_gpu_failed_is_replaced_and_its_chunks_rerun(tmp_path, workers):
    """A worker's GPU context that fails (a sticky CUDA error) makes its episodes' errors the
    process's (no record); a new process has a new context: the driver retires that engine,
    puts its chunk's unfinished episodes back in the queue, starts another engine and finishes
    the plan in the same invocation, one record per episode. The failure is made in the
    engine processes at start-up (`sitecustomize`): the sweep's first action fails as a dead
    context's calls do and the context check says so, in that process only, whose later calls
    fail too."""
    site, flags = tmp_path / "site", tmp_path / "flags"
    site.mkdir()
    flags.mkdir()
    (site / "sitecustomize.py").write_text(GPU_FAILS_ONCE)
    cfg = tmp_path / "processes.yaml"
    text = PROCESSES.replace("mean_s: 0.25", "mean_s: 0.01")
    text = text.replace("max_tasks: 2", f"max_tasks: {workers}")
    text = text.replace("handover_horizontal_block]", "handover_horizontal_block, lift_pot]")
    cfg.write_text(text)
    out = tmp_path / "out"
    path = os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")]))
    done = subprocess.run(
        [sys.executable, "-m", "vabench.sweep", str(cfg), "--out", str(out), "--plain"]
        + ["--no-report"],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=path, VABENCH_TEST_FLAGS=str(flags)),
        timeout=600,
    )
    text = done.stdout + done.stderr
    assert list(flags.glob("failed-*")), text[-3000:]  # the failure happened
    assert done.returncode == 0, text[-3000:]
    assert "is gone: its GPU failed (the CUDA context of cuda:0 failed" in text
    records = ledger_lines(out)
    keys = [(r["task"], r["seed"]) for r in records]
    assert len(keys) == len(set(keys)) == 9
    assert all(r["status"] != "error" for r in records), records
    assert "a second record" not in text and "was not written" not in text  # none sent twice
    # each engine that failed gives back only its own chunk's unfinished episodes (3 a chunk)
    requeued = [
        int(n)
        for n in re.findall(
            r"(\d+) unfinished episodes go back to the queue; starting another", text
        )
    ]
    assert requeued and all(n <= 3 for n in requeued), requeued
