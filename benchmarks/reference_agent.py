"""Per-decision compute time of the reference-servo policy at 1280x960, against the episode's
own cost per step.

    python benchmarks/reference_agent.py [--tasks a,b,...] [--seed S] [--repeats R]

1. Capture: one episode per task (its first verified seed unless --seed; C backend,
   1280x960 JPEG q95, the sweep's image setting) through the engine and the embedded server,
   recording every request the policy received and the episode's wall time.
2. Replay: each recorded request answered `--repeats` times by `reply_text` (the policy's
   whole work: parsing, JPEG decoding, segmentation, planning), timed one by one.

Prints, per task and over all: decisions, median and 99th-percentile policy time, the
episode's wall time per step without the policy (simulation, rendering, HTTP, records on this
machine), and their ratio: how much of a decision's cost the policy adds.
"""

from __future__ import annotations

import argparse
import asyncio
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from vabench.agent.engine import Episode, EpisodeSpec
from vabench.agent.services import task_services
from vabench.llm_pool.config import load_endpoints
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer
from vabench.reference_agent import ReferenceServo, reply_text
from vabench.render.worker import ImageSettings, RenderPool
from vabench.tasks import get_task
from vabench.tasks.manifests import verified_seeds

WIDTH, HEIGHT = 1280, 960
DEFAULT_TASKS = (
    "grasp_single_cube",
    "grasp_single_pen",
    "grasp_single_bottle_upright",
    "click_bell_right",
    "place_cube_in_bowl",
)


class Recording:
    def __init__(self) -> None:
        self.inner = ReferenceServo()
        self.requests: list = []
        self.policy_s = 0.0

    async def respond(self, request):  # type: ignore[no-untyped-def]
        self.requests.append(request)
        t = time.perf_counter()
        reply = await self.inner.respond(request)
        self.policy_s += time.perf_counter() - t
        return reply


async def capture(task_name: str, seed: int, pool: RenderPool, out: Path):  # type: ignore[no-untyped-def]
    task = get_task(task_name)
    policy = Recording()
    spec = EpisodeSpec(task_name, seed, "reference-servo", "active", 0, out / task_name)
    async with LocalServer(policy=policy) as server:
        endpoint = server.endpoint_config("reference-servo", "openai_chat")
        async with (
            LLMPool(load_endpoints([endpoint])) as llm,
            task_services(
                task, 1, llm, pool, backend="c", image=ImageSettings(WIDTH, HEIGHT, 95)
            ) as services,
        ):
            episode = Episode(spec, services)
            t = time.perf_counter()
            result = await episode.run()
            wall = time.perf_counter() - t
    return policy.requests, result, wall, policy.policy_s


def replay(requests: list, repeats: int) -> list[float]:
    times = []
    for request in requests:
        for _ in range(repeats):
            t = time.perf_counter()
            reply_text(request)
            times.append(time.perf_counter() - t)
    return times


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", default=",".join(DEFAULT_TASKS))
    p.add_argument("--seed", type=int)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    rows = []
    all_times: list[float] = []
    with (
        tempfile.TemporaryDirectory() as tmp,
        RenderPool(workers=1, max_size=(WIDTH, HEIGHT), timeout_s=120) as pool,
    ):
        for name in args.tasks.split(","):
            seed = args.seed if args.seed is not None else verified_seeds(name)[0]
            requests, result, wall, policy_s = asyncio.run(capture(name, seed, pool, Path(tmp)))
            times = replay(requests, args.repeats)
            all_times += times
            steps = max(1, result.steps_used)
            env_ms = (wall - policy_s) / steps * 1000
            rows.append((name, seed, result.status, len(requests), times, env_ms))
    print(f"reference_servo policy per decision, {WIDTH}x{HEIGHT} JPEG q95, C backend")
    print(f"{platform.processor() or platform.machine()}, Python {sys.version.split()[0]}")
    header = (
        f"{'task':<30} {'seed':>5} {'result':>8} {'calls':>6} {'median ms':>10} "
        f"{'p99 ms':>8} {'episode ms/step':>16} {'policy/step':>12}"
    )
    print(header)
    print("-" * len(header))
    for name, seed, status, n, times, env_ms in rows:
        med = statistics.median(times) * 1000
        p99 = float(np.percentile(times, 99)) * 1000
        print(
            f"{name:<30} {seed:>5} {status:>8} {n:>6} {med:>10.1f} {p99:>8.1f} "
            f"{env_ms:>16.1f} {med / env_ms:>12.2f}"
        )
    med = statistics.median(all_times) * 1000
    p99 = float(np.percentile(all_times, 99)) * 1000
    env = statistics.mean(r[5] for r in rows)
    print(
        f"{'all':<30} {'':>5} {'':>8} {sum(r[3] for r in rows):>6} {med:>10.1f} {p99:>8.1f} "
        f"{env:>16.1f} {med / env:>12.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
