"""`executor: local` under the one driver: its one engine runs in the driver's own process (no
process, no pipe), its lines reach the ledger through the driver alone, and an engine that
cannot start is not started again in the same process."""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

from vabench.config import load_config
from vabench.config.choices import choose
from vabench.sweep import chunk_engine
from vabench.sweep.local_executor import run_local
from vabench.sweep.plan import plan
from vabench.sweep.rundir import check_run_dir

CONFIG = """\
name: driven
models:
  - {name: local, api: openai_chat, base_url: embedded}
embedded_server: {policy: conversation_hash}
tracks: [active]
summaries: none
tasks: [grasp_single_cube]
seeds: {verified: 2}
runs: 1
step_budget: 2
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
executor: {kind: local}
"""


def _sweep(tmp_path: Path):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG)
    out = tmp_path / "out"
    config = load_config(cfg, overrides={"out": str(out)})
    keys = plan(config)
    check_run_dir(out, config, keys, config.document())
    return config, keys, out


def test_the_engine_runs_in_this_process_and_only_the_driver_writes(tmp_path, monkeypatch, caplog):
    config, keys, out = _sweep(tmp_path)
    sinks: list[bool] = []
    threads: set[str] = set()
    real = chunk_engine.LocalSweep

    class Watched(real):  # type: ignore[misc, valid-type]
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            sinks.append(self.ledger.sink is not None)
            threads.add(threading.current_thread().name)

    monkeypatch.setattr(chunk_engine, "LocalSweep", Watched)
    caplog.set_level(logging.INFO, logger="vabench.sweep.local_executor")
    records = run_local(config, keys, out, choose(config))
    assert len(records) == len(keys) == 2
    assert sinks == [True]  # one chunk, its lines handed to the driver
    assert threads == {"engine"}  # the engine's own thread, not the driver's
    (started,) = [r for r in caplog.records if "engine %d started" in str(r.msg)]
    assert started.args[1]["pid"] == os.getpid()
    assert len((out / "results.jsonl").read_text().splitlines()) == 2
    # the same command again finds nothing to run
    assert run_local(config, keys, out, choose(config)) == records


def test_an_engine_that_cannot_start_is_not_started_again(tmp_path, monkeypatch, caplog):
    config, keys, out = _sweep(tmp_path)
    starts: list[int] = []

    async def broken(self, *args, **kwargs):
        starts.append(1)
        raise RuntimeError("no renderer here")

    monkeypatch.setattr(chunk_engine.ChunkEngine, "start", broken)
    caplog.set_level(logging.INFO, logger="vabench.sweep.local_executor")
    assert run_local(config, keys, out, choose(config)) == {}
    assert starts == [1]
    text = caplog.text
    assert "no renderer here" in text and "no engine is started in its place" in text
    assert "1 chunks failed (2 episodes not run)" in text
