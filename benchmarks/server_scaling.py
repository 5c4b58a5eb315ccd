"""Calls per second of the embedded server answering with the reference agent, against the
processes it runs in (and so the cores it can use): policy worker processes behind one serving
process, or several serving processes on one port.

    python benchmarks/server_scaling.py [--processes 0,1,2] [--server-processes 1,2]
        [--concurrency 32] [--seconds 20] [--tasks a,b] [--json FILE]

1. Capture: one reference-servo episode per task (first verified seed, C backend, 1280x960 JPEG
   q95: the sweep's requests) through the engine and an embedded server that keeps every raw
   request body.
2. Replay: for each setting of `--processes` (`--policy-processes N`: one process serves, N
   compute the replies) and then of `--server-processes` (`--server-processes N`: N processes
   serve on one port, each computing its replies in threads), a fresh
   `python -m vabench.llm_pool.serve --policy reference_servo` (no simulated latency) gets the
   captured bodies from `--concurrency` closed-loop callers over real HTTP on loopback for
   `--seconds` (after a 3 s warm-up). Every reply must be a 200 with a decision.

Prints per setting: calls per second, the ratio to the first setting (one process, the policy
in it), and
the CPU each side used (cores: CPU seconds per wall second, the server's including its policy
workers). The load average before and after is printed too: on a shared machine it decides
how many cores were really there.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import aiohttp

from vabench.agent.engine import Episode, EpisodeSpec
from vabench.agent.services import task_services
from vabench.llm_pool.config import load_endpoints
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.render.worker import ImageSettings, RenderPool
from vabench.tasks import get_task
from vabench.tasks.manifests import verified_seeds

WIDTH, HEIGHT = 1280, 960
DEFAULT_TASKS = ("grasp_single_cube", "place_cube_in_bowl", "grasp_single_pen")


async def capture(task_name: str, pool: RenderPool, out: Path) -> list[bytes]:
    """The raw Chat Completions bodies of one reference-servo episode of `task_name`."""
    task = get_task(task_name)
    seed = verified_seeds(task_name)[0]
    spec = EpisodeSpec(task_name, seed, "reference-servo", "active", 0, out / task_name)
    config = ServerConfig(policy="reference_servo")
    async with LocalServer(config, capture_bodies=True) as server:
        endpoint = server.endpoint_config("reference-servo", "openai_chat")
        async with (
            LLMPool(load_endpoints([endpoint])) as llm,
            task_services(
                task, 1, llm, pool, backend="c", image=ImageSettings(WIDTH, HEIGHT, 95)
            ) as services,
        ):
            await Episode(spec, services).run()
        assert server.bodies is not None
        return [body for _, body in server.bodies]


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process and its reaped and live children."""
    total = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    pids = [pid] + _children(pid)
    for p in pids:
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += sum(int(x) for x in fields[11:15]) / tick  # utime stime cutime cstime
    return total


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(stat.parent.name))
        except (OSError, ValueError):
            continue
    return out


async def load(url: str, bodies: list[bytes], callers: int, seconds: float) -> tuple[int, int]:
    """(calls completed, errors) in `seconds` of `callers` closed-loop clients."""
    done = errors = 0
    stop_at = time.monotonic() + seconds
    connector = aiohttp.TCPConnector(limit=callers)
    headers = {"Content-Type": "application/json"}
    async with aiohttp.ClientSession(connector=connector) as session:

        async def caller(i: int) -> None:
            nonlocal done, errors
            n = i
            while time.monotonic() < stop_at:
                body = bodies[n % len(bodies)]
                n += callers
                async with session.post(url, data=body, headers=headers) as response:
                    reply = await response.json()
                ok = (
                    response.status == 200
                    and "```json" in reply["choices"][0]["message"]["content"]
                )
                if time.monotonic() <= stop_at:
                    done += ok
                    errors += not ok

        await asyncio.gather(*(caller(i) for i in range(callers)))
    return done, errors


def measure(bodies: list[bytes], setting: tuple[str, int], callers: int, seconds: float) -> dict:
    """One setting: ("policy", N) for N policy processes, ("server", N) for N serving ones."""
    kind, processes = setting
    server = subprocess.Popen(
        [sys.executable, "-m", "vabench.llm_pool.serve", "--port", "0"]
        + ["--policy", "reference_servo", f"--{kind}-processes", str(processes)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        line = server.stdout.readline()  # type: ignore[union-attr]
        match = re.search(r"on (http://\S+)", line)
        assert match, line
        url = match.group(1) + "/v1/chat/completions"
        asyncio.run(load(url, bodies, callers, 3.0))  # warm-up: imports, first decodes
        server_cpu0, client_cpu0 = cpu_seconds(server.pid), time.process_time()
        t0 = time.monotonic()
        calls, errors = asyncio.run(load(url, bodies, callers, seconds))
        wall = time.monotonic() - t0
        server_cpu = cpu_seconds(server.pid) - server_cpu0
        client_cpu = time.process_time() - client_cpu0
    finally:
        server.terminate()
        server.wait(timeout=30)
    return {
        f"{kind}_processes": processes,
        "setting": f"{kind} processes {processes}",
        "calls_per_s": calls / wall,
        "errors": errors,
        "server_cores": server_cpu / wall,
        "client_cores": client_cpu / wall,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--processes", default="0,1,2", help="policy worker processes")
    p.add_argument("--server-processes", default="1,2", help="serving processes on one port")
    p.add_argument("--concurrency", type=int, default=32)
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--tasks", default=",".join(DEFAULT_TASKS))
    p.add_argument("--json")
    args = p.parse_args()
    bodies: list[bytes] = []
    with (
        tempfile.TemporaryDirectory() as tmp,
        RenderPool(workers=1, max_size=(WIDTH, HEIGHT), timeout_s=120) as pool,
    ):
        for name in args.tasks.split(","):
            bodies += asyncio.run(capture(name, pool, Path(tmp)))
    size = sum(len(b) for b in bodies) / len(bodies) / 1000
    load_before = os.getloadavg()[0]
    print(
        f"embedded server, reference_servo: {len(bodies)} captured requests ({size:.0f} KB on "
        f"average, {WIDTH}x{HEIGHT}), {args.concurrency} callers, {args.seconds:.0f} s each; "
        f"{os.cpu_count()} CPUs, load average {load_before:.1f} before"
    )
    print(
        f"{'setting':>20} {'calls/s':>8} {'x first':>7} {'server cores':>12} "
        f"{'client cores':>12} {'errors':>6}"
    )
    settings = [("policy", int(x)) for x in args.processes.split(",") if x] + [
        ("server", int(x)) for x in args.server_processes.split(",") if x
    ]
    rows = []
    for setting in settings:
        row = measure(bodies, setting, args.concurrency, args.seconds)
        rows.append(row)
        base = rows[0]["calls_per_s"]
        print(
            f"{row['setting']:>20} {row['calls_per_s']:>8.1f} {row['calls_per_s'] / base:>7.2f} "
            f"{row['server_cores']:>12.2f} {row['client_cores']:>12.2f} {row['errors']:>6}",
            flush=True,
        )
    print(f"load average {os.getloadavg()[0]:.1f} after")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
