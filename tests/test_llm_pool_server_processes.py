"""The embedded server in several processes on one port (`ServerConfig.server_processes`): the
kernel spreads connections over them, the parent sees every request once, replies equal those
of one process, rate limits refuse to be split, and the processes die with their parent."""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import os
import signal
import subprocess
import sys
import time

import aiohttp
import pytest

from tests.test_sweep_reliability import alive, descendants
from vabench.llm_pool.server import LocalServer
from vabench.llm_pool.server_config import ServerConfig, serving_processes

CALLS = 40


def _body(i: int) -> dict:
    return {"model": "m", "messages": [{"role": "user", "content": f"conversation {i}"}]}


async def _call_all(server: LocalServer) -> list[tuple[int, str]]:
    """CALLS requests, each on a new connection (so the kernel picks a process for each)."""
    url = server.base_url("openai_chat") + "/chat/completions"
    connector = aiohttp.TCPConnector(force_close=True)
    async with aiohttp.ClientSession(connector=connector) as session:

        async def one(i: int) -> tuple[int, str]:
            async with session.post(url, json=_body(i)) as response:
                doc = await response.json()
                return response.status, doc["choices"][0]["message"]["content"]

        return list(await asyncio.gather(*(one(i) for i in range(CALLS))))


def _config(processes: int, **extra) -> ServerConfig:
    return ServerConfig(
        policy="conversation_hash",
        latency={"mean_s": 0.01},
        simulate_cache=False,
        server_processes=processes,
        **extra,
    )


def test_processes_share_one_port_and_the_parent_sees_every_request(tmp_path):
    log_path = tmp_path / "requests.jsonl"

    async def run() -> tuple[list[tuple[int, str]], LocalServer, list[tuple[int, str]]]:
        async with LocalServer(_config(2, log_path=str(log_path))) as server:
            assert server.processes == 2
            replies = await _call_all(server)
            deadline = time.monotonic() + 10
            while len(server.log) < CALLS and time.monotonic() < deadline:
                await asyncio.sleep(0.05)  # records arrive through the pipe
        async with LocalServer(_config(0)) as one:
            alone = await _call_all(one)
        return replies, server, alone

    replies, server, alone = asyncio.run(run())
    assert [status for status, _ in replies] == [200] * CALLS
    assert sorted(r.id for r in server.log) == list(range(1, CALLS + 1))
    served = collections.Counter(r.process for r in server.log)
    assert set(served) == {0, 1}, f"one process served every connection: {served}"
    assert server.counts["status:200"] == CALLS
    lines = [json.loads(x) for x in log_path.read_text().splitlines()]
    assert len(lines) == CALLS and all(x["status"] == 200 for x in lines)
    # the policy is a function of each conversation: the processes answer as one does
    assert replies == alone


def test_rate_limits_and_in_process_features_need_one_process(monkeypatch):
    with pytest.raises(ValueError, match="server_processes: rpm is enforced by one process"):
        ServerConfig(server_processes=2, rpm=60)
    with pytest.raises(ValueError, match="server_processes: rpm and tpm are enforced"):
        ServerConfig(server_processes=1, rpm=60, tpm=1000)
    with pytest.raises(ValueError, match="server_processes: a policy object or captured bodies"):
        LocalServer(_config(2), capture_bodies=True)
    monkeypatch.setenv("VABENCH_CORES", "8")
    assert serving_processes(ServerConfig(policy="reference_servo", server_processes="auto")) == 4
    # a stateful policy, or a limit that must see every request: served in the caller's loop
    assert serving_processes(ServerConfig(policy="random_action", server_processes="auto")) == 0
    limited = ServerConfig(policy="conversation_hash", server_processes="auto", rpm=60)
    assert serving_processes(limited) == 0
    monkeypatch.setenv("VABENCH_CORES", "2")
    assert serving_processes(ServerConfig(policy="reference_servo", server_processes="auto")) == 0


SERVE_AND_WAIT = """
import asyncio, sys
from vabench.llm_pool.server import LocalServer, ServerConfig

async def main():
    async with LocalServer(ServerConfig(policy="conversation_hash", server_processes=2)) as s:
        print(s.url, flush=True)
        await asyncio.sleep(600)

if __name__ == "__main__":
    asyncio.run(main())
"""


def test_serving_processes_end_with_their_parent(tmp_path):
    script = tmp_path / "serve_and_wait.py"
    script.write_text(SERVE_AND_WAIT)
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    proc = subprocess.Popen(
        [sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env
    )
    children: set[int] = set()
    try:
        assert proc.stdout is not None and proc.stdout.readline().startswith("http://")
        children = descendants(proc.pid)
        assert len(children) >= 2
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 30
        while any(alive(p) for p in children):
            assert time.monotonic() < deadline, "a serving process outlived its parent"
            time.sleep(0.1)
    finally:
        for pid in [proc.pid, *children]:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
        if proc.stdout is not None:
            proc.stdout.close()


SWEEP = """\
name: served
models:
  - {{name: local, api: openai_chat, base_url: embedded}}
embedded_server: {{policy: conversation_hash, simulate_cache: false, server_processes: {n}}}
tracks: [active]
tasks: [grasp_single_cube]
seeds: {{verified: 2}}
runs: 1
step_budget: 3
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
executor: {{kind: local}}
"""


def test_a_sweep_served_by_processes_records_what_one_process_does(tmp_path, caplog):
    from tests.test_sweep_processes import records
    from vabench.sweep.__main__ import main

    outs = []
    for n, served_by in ((0, "in this process"), (2, "by 2 processes")):
        cfg = tmp_path / f"served{n}.yaml"
        cfg.write_text(SWEEP.format(n=n))
        outs.append(tmp_path / f"out{n}")
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="vabench.sweep.runner"):
            assert main([str(cfg), "--out", str(outs[-1]), "--plain", "--no-report"]) == 0
        assert f"served {served_by}" in caplog.text
    alone, served = (records(out) for out in outs)
    assert served == alone and len(served) == 2
