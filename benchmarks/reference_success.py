"""Success of the reference-servo agent per family: the episodes a sweep would run, in one
process, with every episode's records kept for inspection.

    python benchmarks/reference_success.py --tasks grasp_single_cube,lift_pot \
        [--protocol active|passive] [--seeds 20 | --seeds 1000,1003] [--size 640x480] \
        [--slots 2] [--out DIR] [--json FILE]

Each task's verified seeds (`configs/seeds/<task>.json`, the first N with `--seeds N`) run
through the engine (`vabench.agent.engine`) and the embedded server over loopback HTTP, as the
sweep calls a model: C MuJoCo backend, JPEG q95. Prints one line per episode (status, steps,
checkpoints reached) and a table per family: successes / episodes and, for the basket,
objects placed. The agent is deterministic and so is the C simulator, so one run per seed
measures it. `--out DIR` keeps each episode's events.jsonl (the agent's replies, with their
memo) and the frames it saw.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

from vabench.agent.engine import EpisodeSpec, run_episodes
from vabench.agent.records import EpisodeResult
from vabench.agent.services import task_services
from vabench.llm_pool.config import load_endpoints
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer
from vabench.reference_agent import ReferenceServo
from vabench.render.worker import ImageSettings, RenderPool
from vabench.tasks import get_task
from vabench.tasks.manifests import verified_seeds

MODEL = "reference-servo"


def seeds_of(task: str, spec: str) -> list[int]:
    if "," in spec or spec.startswith("s"):
        return [int(s) for s in spec.lstrip("s").split(",") if s]
    return list(verified_seeds(task))[: int(spec)]


async def run_task(
    task_name: str,
    seeds: list[int],
    protocol: str,
    size: tuple[int, int],
    slots: int,
    pool: RenderPool,
    out: Path,
) -> list[EpisodeResult]:
    task = get_task(task_name)
    specs = [
        EpisodeSpec(task_name, s, MODEL, protocol, 0, out / protocol / task_name / f"seed_{s}")  # type: ignore[arg-type]
        for s in seeds
    ]
    async with LocalServer(policy=ReferenceServo()) as server:
        endpoint = server.endpoint_config(MODEL, "openai_chat")
        async with (
            LLMPool(load_endpoints([endpoint])) as llm,
            task_services(
                task,
                min(slots, len(seeds)),
                llm,
                pool,
                backend="c",
                image=ImageSettings(size[0], size[1], 95),
            ) as services,
        ):
            return await run_episodes(specs, services)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", required=True)
    p.add_argument("--protocol", default="active", choices=("active", "passive"))
    p.add_argument("--seeds", default="20", help="N (the first N verified) or s1,s2,...")
    p.add_argument("--size", default="640x480")
    p.add_argument("--slots", type=int, default=2, help="episodes of a task at once")
    p.add_argument("--out", help="keep the episodes' records here")
    p.add_argument("--json", help="append one JSON line per family to this file")
    args = p.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    tmp = None
    if args.out is None:
        tmp = tempfile.TemporaryDirectory()
    out = Path(args.out or tmp.name)  # type: ignore[union-attr]
    rows = []
    print(
        f"reference-servo, {args.protocol} protocol, C backend, {w}x{h} JPEG q95, "
        f"{platform.machine()} {datetime.date.today()}",
        flush=True,
    )
    with RenderPool(workers=1, max_size=(w, h), timeout_s=300) as pool:
        for name in args.tasks.split(","):
            seeds = seeds_of(name, args.seeds)
            t = time.perf_counter()
            results = asyncio.run(
                run_task(name, seeds, args.protocol, (w, h), args.slots, pool, out)
            )
            wall = time.perf_counter() - t
            for r in sorted(results, key=lambda r: r.seed):
                print(
                    f"  {name} {r.seed}: {r.status:<8} {r.stop_reason:<16} steps "
                    f"{r.steps_used:>3} progress {r.progress}/{r.n_checkpoints}",
                    flush=True,
                )
            ok = sum(r.success for r in results)
            placed = sum(r.progress for r in results)
            failed = [r.seed for r in results if not r.success]
            row = {
                "task": name,
                "protocol": args.protocol,
                "size": f"{w}x{h}",
                "successes": ok,
                "episodes": len(results),
                "progress": placed,
                "possible": sum(r.n_checkpoints for r in results),
                "failed_seeds": failed,
                "wall_s": round(wall, 1),
                "date": str(datetime.date.today()),
            }
            rows.append(row)
            print(
                f"{name}: {ok}/{len(results)} (progress {placed}/{row['possible']}) "
                f"failed {failed} in {wall:.0f} s",
                flush=True,
            )
            if args.json:
                with open(args.json, "a") as f:
                    f.write(json.dumps(row) + "\n")
    print("\n| family | successes | failed seeds |\n|---|---|---|")
    for r in rows:
        print(
            f"| {r['task']} | {r['successes']}/{r['episodes']} | "
            f"{', '.join(map(str, r['failed_seeds'])) or '-'} |"
        )
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
