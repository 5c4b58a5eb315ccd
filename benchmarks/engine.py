"""Episode engine throughput against the ideal set by model latency alone.

    python benchmarks/engine.py [--backend c|warp|mjx] [--renderer gl|warp]
        [--concurrency 1,10,100,1000] [--latency 2] [--steps 5] [--size 640x480]
        [--render-workers 2] [--task grasp_single_cube] [--shared-batch]
        [--sim-window 0.01,0.1] [--json FILE]

On a GPU host the product's path is `--backend warp --renderer warp` (MuJoCo Warp physics,
Warp's ray tracer reading the batch's state on the device; the old `--backend mjx --impl warp`
says the same).

For each concurrency C, C episodes of one task run at once against the embedded server (random
valid robot actions, every reply after exactly `--latency` seconds), each for `--steps`
decisions. With no simulator and no renderer an episode would take steps * latency, so C
episodes would finish in that time: the ideal. Printed per C: measured wall time and episodes
per hour, their ratio to the ideal, the harness overhead per decision (wall / steps - latency),
and where the time went: simulator busy seconds per decision (resets + batched actions), render
busy seconds per observation, mean simulator and render batch sizes, and the CPU time of this
process per decision (engine, model client and, unless `--server-processes N` serves it in
processes of its own, the embedded server; render workers excluded) and of its event loop's
thread alone ("loop ms/dec": the engine, the model client, the agent's bookkeeping, everything
that holds the GIL on that thread; physics and JPEG threads excluded): 1 / the larger of the two
bounds the decisions per second one engine process can drive.

`--sim-window` (seconds, a list: each C is run once per value) is the simulator's batching
window (`simulator.window_s` of a config): how long the first action of a physics call waits
for others. A call steps every slot of the batch whatever the number of actions in it (idle
slots frozen), so a longer window trades each decision's wait for fewer whole-batch calls.

`--shared-batch` runs every C on one batch of max(C) slots (one MJX compile; idle slots
frozen), as a sweep does; otherwise each C gets a batch of exactly C slots. Compilation and
renderer start-up are excluded: each batch runs one untimed warm-up round first.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


async def run_level(task, n_episodes, steps, latency, svc_factory, seeds):
    from vabench.agent.engine import EpisodeSpec, run_episodes

    async with svc_factory() as svc:
        warm = [EpisodeSpec(task.name, seeds[0], "local", step_budget=1)]
        await run_episodes(warm, svc)  # compile and warm the workers, untimed
        sim0 = (svc.sim.stats.busy_s, svc.sim.stats.calls, svc.sim.stats.items)
        ren0 = (svc.render.stats.busy_s, svc.render.stats.calls, svc.render.stats.items)
        specs = [
            EpisodeSpec(task.name, seeds[i % len(seeds)], "local", step_budget=steps)
            for i in range(n_episodes)
        ]
        t0, cpu0, loop0 = time.perf_counter(), time.process_time(), time.thread_time()
        results = await run_episodes(specs, svc)
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        loop_cpu = time.thread_time() - loop0  # this coroutine runs on the event loop's thread
        sim = [
            a - b
            for a, b in zip(
                (svc.sim.stats.busy_s, svc.sim.stats.calls, svc.sim.stats.items), sim0, strict=True
            )
        ]
        ren = [
            a - b
            for a, b in zip(
                (svc.render.stats.busy_s, svc.render.stats.calls, svc.render.stats.items),
                ren0,
                strict=True,
            )
        ]
    decisions = sum(r.steps_used for r in results)
    bad = [r for r in results if not r.scored]
    return dict(
        episodes=n_episodes,
        wall_s=wall,
        ideal_s=steps * latency,
        decisions=decisions,
        episodes_per_hour=n_episodes / wall * 3600,
        ideal_episodes_per_hour=n_episodes / (steps * latency) * 3600,
        ratio=steps * latency / wall,
        overhead_per_decision_s=wall / steps - latency,
        engine_cpu_per_decision_s=cpu / max(decisions, 1),
        loop_cpu_per_decision_s=loop_cpu / max(decisions, 1),
        sim_busy_per_decision_s=sim[0] / max(decisions, 1),
        sim_calls=sim[1],
        sim_mean_batch=sim[2] / max(sim[1], 1),
        render_busy_per_image_s=ren[0] / max(ren[2], 1),
        render_calls=ren[1],
        render_mean_batch=ren[2] / max(ren[1], 1),
        errors=len(bad),
        error_examples=[r.error for r in bad[:2]],
    )


async def main_async(args) -> list[dict]:
    import contextlib

    from vabench.agent.services import task_services
    from vabench.llm_pool.pool import LLMPool
    from vabench.llm_pool.server import LocalServer, ServerConfig
    from vabench.render.backends import make_renderer
    from vabench.render.worker import ImageSettings
    from vabench.tasks import get_task
    from vabench.tasks.manifests import verified_seeds

    task = get_task(args.task)
    seeds = verified_seeds(task.name)
    levels = [int(c) for c in args.concurrency.split(",")]
    windows = [float(w) for w in args.sim_window.split(",")]
    if args.shared_batch and len(windows) > 1:
        raise SystemExit("--sim-window: one value with --shared-batch (the batch is built once)")
    width, height = (int(v) for v in args.size.split("x"))
    image = ImageSettings(width, height, 95)
    # random_action keeps a seeded state: served by processes it gets one per process
    config = ServerConfig(
        policy="random_action",
        policy_options={"seed": 1},
        latency={"mean_s": args.latency, "dist": "fixed"},
        server_processes=args.server_processes,
    )
    batch_kwargs: dict = {"lanes": args.lanes} if args.lanes else {}
    batch_kwargs["backend"] = args.physics.value
    rows = []
    renderer, choice = make_renderer(
        args.renderer, workers=args.render_workers, platform=args.platform, max_size=(width, height)
    )
    with renderer as rp:
        described = (
            f"{args.render_workers} x {rp.gl_info}" if choice.backend == "gl" else "Warp ray tracer"
        )
        print(
            f"renderer: {described}; backend {args.physics.label}; "
            f"latency {args.latency} s; {args.steps} decisions per episode; {args.size}; "
            f"model server {args.server_processes or 'in this'} process(es)"
        )
        async with LocalServer(config) as server:
            endpoint = server.endpoint_config(
                "local", "openai_chat", limits={"max_concurrency": max(levels) + 8}
            )
            async with LLMPool([endpoint]) as llm, contextlib.AsyncExitStack() as stack:
                shared = None
                if args.shared_batch:
                    shared = await stack.enter_async_context(
                        task_services(
                            task,
                            max(levels),
                            llm,
                            rp,
                            image=image,
                            sim_window_s=windows[0],
                            **batch_kwargs,
                        )
                    )

                print(
                    f"{'C':>5} {'win s':>6} {'wall s':>8} {'ideal s':>8} {'x ideal':>8} "
                    f"{'ep/h':>9} {'ovh/dec s':>9} {'sim s/dec':>9} {'sim bat':>7} "
                    f"{'ren s/img':>9} {'ren bat':>7} {'cpu ms/dec':>10} {'loop ms/dec':>11} "
                    f"{'err':>4}"
                )
                for c, window in [(c, w) for c in levels for w in windows]:

                    def factory(c=c, window=window):
                        if shared is not None:

                            @contextlib.asynccontextmanager
                            async def reuse():
                                yield shared

                            return reuse()
                        return task_services(
                            task, c, llm, rp, image=image, sim_window_s=window, **batch_kwargs
                        )

                    row = await run_level(task, c, args.steps, args.latency, factory, seeds)
                    row.update(
                        concurrency=c,
                        sim_window_s=window,
                        backend=args.physics.backend,
                        lanes=args.lanes,
                        shared_batch=args.shared_batch,
                        size=args.size,
                        latency_s=args.latency,
                        renderer=described,
                    )
                    rows.append(row)
                    print(
                        f"{c:>5} {window:>6.3f} {row['wall_s']:>8.1f} {row['ideal_s']:>8.1f} "
                        f"{row['ratio']:>8.2f} {row['episodes_per_hour']:>9.0f} "
                        f"{row['overhead_per_decision_s']:>9.3f} "
                        f"{row['sim_busy_per_decision_s']:>9.4f} {row['sim_mean_batch']:>7.1f} "
                        f"{row['render_busy_per_image_s']:>9.4f} "
                        f"{row['render_mean_batch']:>7.1f} "
                        f"{row['engine_cpu_per_decision_s'] * 1000:>10.2f} "
                        f"{row['loop_cpu_per_decision_s'] * 1000:>11.2f} {row['errors']:>4}",
                        flush=True,
                    )
    return rows


def main() -> None:
    from vabench.sim_mjx.cli import add_physics_arguments, physics_of

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--task", default="grasp_single_cube")
    add_physics_arguments(p, backend="c")
    p.add_argument("--renderer", choices=("gl", "warp"), default="gl")
    p.add_argument("--concurrency", default="1,10,100,1000")
    p.add_argument("--latency", type=float, default=2.0)
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--size", default="640x480")
    p.add_argument("--render-workers", type=int, default=2)
    p.add_argument("--platform", default="auto", choices=("auto", "egl", "osmesa"))
    p.add_argument("--shared-batch", action="store_true")
    p.add_argument(
        "--sim-window",
        default="0.01",
        help="the simulator's batching window in seconds, a comma list (default 0.01, a "
        "config's simulator.window_s default)",
    )
    p.add_argument(
        "--server-processes",
        type=int,
        default=0,
        help="serve the model in N processes of its own (default 0: in this process, so the "
        "CPU per decision counts the server's work too)",
    )
    p.add_argument("--lanes", type=int, help="MJX: physics lanes (default: the batch's)")
    p.add_argument("--json")
    args = p.parse_args()
    args.physics = physics_of(p, args)
    rows = asyncio.run(main_async(args))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
