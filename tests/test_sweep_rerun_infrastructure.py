"""Infrastructure errors are not final, through the real sweep command on C MuJoCo: a first run
against an endpoint that answers every call with a 500 ends each episode as an
`infrastructure_error`; the same command, the endpoint healthy again, runs those episodes
again (each recorded once, its earlier attempts kept in infrastructure.jsonl and set aside in
its directory); `--no-retry-infrastructure` keeps them as they were.
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from vabench.llm_pool.faults import FaultConfig, FaultPlan
from vabench.llm_pool.server import ServerConfig
from vabench.llm_pool.testing import server_in_thread
from vabench.run_layout import INFRASTRUCTURE, RESULTS
from vabench.sweep.__main__ import main

CONFIG = """\
name: rerun
models:
  - name: flaky
    api: openai_chat
    base_url: {url}
    retry: {{max_attempts: 2, backoff_base_s: 0.01, backoff_max_s: 0.02}}
tracks: [active]
tasks: [grasp_single_cube]
seeds: {{verified: 2}}
runs: 1
step_budget: 2
retries: {{infrastructure_rounds: 0}}
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
executor: {{kind: local}}
"""


def lines(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


@pytest.mark.parametrize("keep", [False, True])
def test_the_same_command_reruns_infrastructure_errors_unless_told_to_keep_them(tmp_path, keep):
    failing = ServerConfig(policy="conversation_hash", faults={"rates": {"server_error": 1.0}})
    with server_in_thread(failing) as server:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(CONFIG.format(url=server.base_url("openai_chat")))
        out = tmp_path / "out"
        command = [str(cfg), "--out", str(out), "--plain", "--no-report"]
        assert main(command) == 1  # every episode unscored, listed
        first = lines(out / RESULTS)
        assert len(first) == 2 and {r["status"] for r in first} == {"infrastructure_error"}

        server.faults = FaultPlan(FaultConfig(), random.Random(0))  # healthy again
        again = command + (["--no-retry-infrastructure"] if keep else [])
        assert main(again) == (1 if keep else 0)
    records = lines(out / RESULTS)
    keys = [(r["seed"], r["run"]) for r in records]
    assert len(records) == 2 and len(set(keys)) == 2  # each episode recorded once
    if keep:
        assert records == first
        assert not lines(out / INFRASTRUCTURE)
        return
    assert {r["status"] for r in records} <= {"success", "failure"}
    attempts = lines(out / INFRASTRUCTURE)
    assert len(attempts) == 2 and all(a["reopened"] for a in attempts)
    assert {(a["seed"], a["run"]) for a in attempts} == set(keys)
    for record in records:  # the failed attempt's files kept beside the new ones
        episode = out / record["episode_dir"]
        assert (episode / "result.json").exists()
        kept = [p for p in episode.iterdir() if p.is_dir() and (p / "result.json").exists()]
        assert len(kept) == 1
        assert json.loads((kept[0] / "result.json").read_text())["status"] == (
            "infrastructure_error"
        )
