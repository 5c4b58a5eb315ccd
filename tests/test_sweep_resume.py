"""A sweep killed with SIGKILL in the middle and run again ends exactly like an uninterrupted
one: one record per planned episode, the same outcomes, the same report.

The model is the embedded server's `conversation_hash` policy: each episode's decisions are a
function of its own conversation, so interleaving and resumption cannot change them.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vabench.agent.records import read_events

CONFIG = """\
name: resume
models:
  - {name: local, api: openai_chat, base_url: embedded}
embedded_server: {policy: conversation_hash, latency: {mean_s: 0.05}, simulate_cache: false}
tracks: [active, passive]
tasks: [grasp_single_cube, handover_horizontal_block]
seeds: {verified: 2}
runs: 2
step_budget: 4
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
executor: {max_tasks: 2}
"""
PLANNED = 1 * 2 * 2 * 2 * 2
# Fields that measure time or host load, not outcome.
TIMING = {"wall_s", "started_at"}


def sweep(config: Path, out: Path, **kwargs) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(
        [sys.executable, "-m", "vabench.sweep", str(config), "--out", str(out), "--plain"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        start_new_session=True,
        **kwargs,
    )


def finish(proc: subprocess.Popen, timeout: float = 300) -> str:
    out, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, out[-3000:]
    return out


def records(run_dir: Path) -> dict[tuple, dict]:
    lines = (run_dir / "results.jsonl").read_text().splitlines()
    out = {}
    for line in lines:
        r = json.loads(line)
        key = (r["model"], r["track"], r["task"], r["seed"], r["run"])
        assert key not in out, f"two records for {key}"
        out[key] = {k: v for k, v in r.items() if k not in TIMING}
    return out


def lines_in(path: Path) -> int:
    return len(path.read_text().splitlines()) if path.exists() else 0


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "resume.yaml"
    path.write_text(CONFIG)
    return path


def test_killed_sweep_resumes_to_the_uninterrupted_result(config, tmp_path):
    straight, killed = tmp_path / "straight", tmp_path / "killed"
    finish(sweep(config, straight))

    proc = sweep(config, killed)
    deadline = time.monotonic() + 240
    while lines_in(killed / "results.jsonl") < 3:
        assert proc.poll() is None, proc.communicate()[0][-3000:]
        assert time.monotonic() < deadline, "the sweep recorded nothing in time"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # the sweep, its render worker, everything
    proc.wait()
    partial = lines_in(killed / "results.jsonl")
    assert 3 <= partial < PLANNED

    out = finish(sweep(config, killed))
    a, b = records(straight), records(killed)
    assert len(a) == len(b) == PLANNED
    assert a == b
    assert (straight / "report" / "report.html").exists(), out[-2000:]
    tables = sorted((straight / "report").glob("*.md")) + sorted(
        (straight / "report").glob("*.csv")
    )
    assert tables
    for table in tables:
        if table.stem == "spend":  # the bill differs: the killed run paid for its lost attempts
            continue
        mine = (killed / "report" / table.name).read_text().replace(str(killed), "RUN")
        assert without_bill(mine) == without_bill(
            table.read_text().replace(str(straight), "RUN")
        ), table.name
    # ...and says so: the interrupted attempts' calls are in the bill, nothing else differs
    bill = {r["source"]: r for r in csv.DictReader((killed / "report" / "spend.csv").open())}
    straight_bill = {
        r["source"]: r for r in csv.DictReader((straight / "report" / "spend.csv").open())
    }
    logged = sum(
        e["usage"]["input_tokens"]
        for partial in (killed / "episodes").rglob("partial_*")
        for e in read_events(partial)
        if e["type"] == "reply"
    )
    row = bill.get("interrupted attempts", {"tokens_input": "0"})
    assert int(row["tokens_input"]) == logged
    assert bill["scored episodes"] == straight_bill["scored episodes"]


def without_bill(markdown: str) -> str:
    """A report without its "Spend of every call" section."""
    head, sep, tail = markdown.partition("## Spend of every call")
    if not sep:
        return markdown
    rest = tail.split("\n## ", 1)
    return head + ("## " + rest[1] if len(rest) > 1 else "")
