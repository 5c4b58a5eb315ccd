"""The sweep runner in process: infrastructure failures get their retry rounds and end listed,
never scored; a result.json that never reached the ledger is adopted, not run again; a cut
ledger line is dropped; a second record of an episode is collapsed and reported; a bad config
stops the command before any call."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

from vabench.config import load_config
from vabench.config.choices import choose
from vabench.run_layout import DUPLICATES, INFRASTRUCTURE, RESULTS
from vabench.sweep.__main__ import main
from vabench.sweep.plan import plan
from vabench.sweep.results import Ledger, key_of
from vabench.sweep.runner import LocalSweep

BASE = """\
name: t
models:
  - name: local
    api: openai_chat
    base_url: embedded
    retry: {{max_attempts: 1}}
embedded_server: {server}
tracks: [active]
tasks: [grasp_single_cube]
seeds: {{verified: 2}}
runs: 1
step_budget: 2
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
retries: {{infrastructure_rounds: 2}}
"""


def write_config(tmp_path: Path, server: str) -> Path:
    path = tmp_path / "sweep.yaml"
    path.write_text(BASE.format(server=server))
    return path


def run(config_path: Path, out: Path) -> LocalSweep:
    config = load_config(config_path, overrides={"out": str(out)})
    sweep = LocalSweep(config, plan(config), out, choose(config))
    asyncio.run(sweep.run())
    return sweep


def test_infrastructure_failures_are_retried_then_listed_unscored(tmp_path):
    cfg = write_config(tmp_path, "{policy: random_action, faults: {rates: {server_error: 1.0}}}")
    sweep = run(cfg, tmp_path / "out")
    records = sweep.ledger.records
    assert len(records) == 2
    assert all(r["status"] == "infrastructure_error" and not r["success"] for r in records.values())
    # 1 + 2 rounds = 3 attempts each: 2 logged as retried, the third recorded in the ledger
    infra = (tmp_path / "out" / INFRASTRUCTURE).read_text().splitlines()
    assert len(infra) == 2 * 2
    episode = tmp_path / "out" / next(iter(records.values()))["episode_dir"]
    assert (episode / "result.json").exists()
    assert (episode / "attempt_1" / "result.json").exists()
    assert (episode / "attempt_2" / "result.json").exists()
    # a rerun changes nothing: every planned episode already has its record
    again = run(cfg, tmp_path / "out")
    assert again.ledger.records == records


def test_orphaned_result_is_adopted_and_a_cut_line_dropped(tmp_path):
    cfg = write_config(tmp_path, "{policy: conversation_hash}")
    out = tmp_path / "out"
    first = run(cfg, out)
    ledger = out / RESULTS
    lines = ledger.read_text().splitlines(keepends=True)
    assert len(lines) == 2
    # Lose the second record as a kill would: half of its line written, result.json on disk.
    ledger.write_text(lines[0] + lines[1][: len(lines[1]) // 2])
    episode = out / json.loads(lines[1])["episode_dir"]
    result_before = (episode / "result.json").read_text()
    second = run(cfg, out)
    assert second.ledger.records == first.ledger.records
    assert (episode / "result.json").read_text() == result_before  # adopted, not re-run
    assert len(ledger.read_text().splitlines()) == 2


def test_a_second_record_for_one_episode_is_collapsed_and_reported(tmp_path):
    """Two writers raced (a worker of a killed sweep and its resumption): resuming keeps the
    first record, reports the second and moves it aside (its spend still counts), never
    refuses the run directory; a repeated open moves nothing twice."""
    cfg = write_config(tmp_path, "{policy: conversation_hash}")
    out = tmp_path / "out"
    first = run(cfg, out)
    original = (out / RESULTS).read_bytes()
    line = original.decode().splitlines()[0]
    second = json.loads(line) | {"cost_usd": 1.5, "wall_s": 99.0}
    with open(out / RESULTS, "a") as f:
        f.write(json.dumps(second) + "\n")
    for _ in range(2):
        ledger = Ledger.open(out)
        assert ledger.records == first.ledger.records
        assert (out / RESULTS).read_bytes() == original
        assert [json.loads(x) for x in (out / DUPLICATES).read_text().splitlines()] == [second]
    key = "/".join(map(str, key_of(second)))
    assert len(ledger.collapsed) == 0  # the second open found nothing left to collapse
    with open(out / RESULTS, "a") as f:
        f.write(json.dumps(second) + "\n")
    again = run(cfg, out)  # a resume reports it and runs nothing
    assert again.ledger.collapsed and key in again.ledger.collapsed[0]
    assert again.ledger.records == first.ledger.records
    assert len((out / DUPLICATES).read_text().splitlines()) == 1


def test_bad_config_stops_before_any_call(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(
        BASE.format(server="{policy: random_action}")
        .replace("tasks: [grasp_single_cube]", "tasks: [grasp_single_cub]")
        .replace("runs: 1", "runz: 1")
    )
    assert main([str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "grasp_single_cub" in err and "runz" in err
    assert not (tmp_path / "out").exists()


def _engine_config(tmp_path: Path):
    config = load_config(
        write_config(tmp_path, "{policy: conversation_hash, server_processes: 1}"),
        overrides={"out": str(tmp_path / "run")},
    )
    return config, choose(config)


def test_the_renderer_starts_while_the_embedded_server_starts(tmp_path, monkeypatch):
    """An engine's renderer and its embedded server start side by side (one after the other
    before: ~3 s each of an engine process's start on an H100 host)."""
    import time

    from vabench.llm_pool.server import LocalServer
    from vabench.render.worker import RenderPool
    from vabench.sweep.runner import open_engine

    server_up: list[float] = []
    server_start, renderer_start = LocalServer.start, RenderPool.start

    async def timed_server_start(self, *args, **kwargs):
        out = await server_start(self, *args, **kwargs)
        server_up.append(time.monotonic())
        return out

    began: list[float] = []

    ended: list[float] = []

    def timed_renderer_start(self):
        began.append(time.monotonic())
        out = renderer_start(self)
        ended.append(time.monotonic())
        return out

    monkeypatch.setattr(LocalServer, "start", timed_server_start)
    monkeypatch.setattr(RenderPool, "start", timed_renderer_start)
    config, choices = _engine_config(tmp_path)

    async def open_and_close():
        async with open_engine(config, choices, tmp_path / "run"):
            assert ended, "the engine was handed out before its renderer had started"

    asyncio.run(open_and_close())
    assert began and server_up and began[0] < server_up[0]


def test_a_renderer_that_cannot_start_stops_the_engine_with_its_error(tmp_path, monkeypatch):
    """The renderer's error is the engine's, and the embedded server started beside it is
    stopped (its processes gone), the renderer closed once its start has ended."""
    import pytest

    from vabench.llm_pool.server_processes import ServingProcesses
    from vabench.render.images import RenderError
    from vabench.render.worker import RenderPool
    from vabench.sweep.runner import open_engine

    served: list[ServingProcesses] = []
    closed: list[bool] = []
    serving_start, renderer_close = ServingProcesses.start, RenderPool.close

    def kept_serving_start(self, host, port):
        served.append(self)
        return serving_start(self, host, port)

    def failing_start(self):
        raise RenderError("no display for GL (made up by the test)")

    def counted_close(self):
        closed.append(True)
        renderer_close(self)

    monkeypatch.setattr(ServingProcesses, "start", kept_serving_start)
    monkeypatch.setattr(RenderPool, "start", failing_start)
    monkeypatch.setattr(RenderPool, "close", counted_close)
    config, choices = _engine_config(tmp_path)

    async def open_engine_once():
        async with open_engine(config, choices, tmp_path / "run"):
            raise AssertionError("the engine opened without a renderer")

    with pytest.raises(RenderError, match="no display for GL"):
        asyncio.run(open_engine_once())
    assert closed == [True]
    (serving,) = served
    assert serving._processes and not any(p.is_alive() for p in serving._processes)
