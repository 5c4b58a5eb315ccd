"""Episode engine throughput against the ideal set by model latency alone.

    python benchmarks/engine.py [--backend c|warp|mjx] [--renderer gl|warp]
        [--concurrency 1,10,100,1000] [--latency 2] [--steps 5] [--size 640x480]
        [--render-workers 2] [--task grasp_single_cube] [--shared-batch]
        [--sim-window 0.01,0.1] [--processes 1,4] [--json FILE]

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

`--processes` (a list) deals each round's C episodes over that many engine processes, each
with its own batch, renderer and model client against the one embedded server, as the sweep's
`processes` executor runs them (on a GPU under a CUDA MPS daemon of the benchmark's own, so that
their kernels run side by side); they start their round together once each has warmed up, and
the wall time is this process's, from that start to the last one's totals. Why: one engine
process is bounded by its host side, ~2-3 ms of CPU a decision (request building, base64, JSON,
HTTP, bookkeeping) under one interpreter lock, ~350-500 decisions/s (an H200, 2026-11-29),
while C = 2,000 at L = 2 s asks for 1,000. The CPU columns are then per decision over all the
engine processes, "cpu" with this process's own over the round (the embedded server's, where
it runs here, as in a one-process row), "loop" over the engine processes' event loops. A row
with more processes than episodes is skipped; the JSON is written after every row.

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

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from engine_rounds import measure, run_in_processes, summarize

HEADER = (
    f"{'C':>5} {'proc':>4} {'win s':>6} {'wall s':>8} {'ideal s':>8} {'x ideal':>8} "
    f"{'ep/h':>9} {'ovh/dec s':>9} {'sim s/dec':>9} {'sim bat':>7} "
    f"{'ren s/img':>9} {'ren bat':>7} {'cpu ms/dec':>10} {'loop ms/dec':>11} {'err':>4}"
)


def row_line(row) -> str:
    return (
        f"{row['concurrency']:>5} {row['processes']:>4} {row['sim_window_s']:>6.3f} "
        f"{row['wall_s']:>8.1f} {row['ideal_s']:>8.1f} {row['ratio']:>8.2f} "
        f"{row['episodes_per_hour']:>9.0f} {row['overhead_per_decision_s']:>9.3f} "
        f"{row['sim_busy_per_decision_s']:>9.4f} {row['sim_mean_batch']:>7.1f} "
        f"{row['render_busy_per_image_s']:>9.4f} {row['render_mean_batch']:>7.1f} "
        f"{row['engine_cpu_per_decision_s'] * 1000:>10.2f} "
        f"{row['loop_cpu_per_decision_s'] * 1000:>11.2f} {row['errors']:>4}"
    )


def gpu_clients(args, processes):
    """CUDA MPS for the rows of several engine processes on a GPU, as the sweep's `processes`
    executor runs them (`vabench.tuning.mps`: a daemon of our own; this process is no client).
    Returns the daemon's context, what the line says of it, and `env_for(n)`: the variables each
    of n engine processes starts with (the daemon's, its GPU numbering, and each process's share
    of the GPU and the cores, `VABENCH_GPU_SHARE`, `VABENCH_CORES`)."""
    import contextlib

    from vabench.children import CORES_VARIABLE
    from vabench.config.choices import this_machine
    from vabench.sim_mjx.warp.device import GPU_SHARE
    from vabench.tuning import mps

    stack = contextlib.ExitStack()
    machine = this_machine()
    on_gpu = args.renderer == "warp" or args.physics.is_warp
    clients: dict = {}
    said = "no MPS"
    if on_gpu and max(processes) > 1:
        try:
            clients = stack.enter_context(mps.private_daemon())
            said = "CUDA MPS"
        except mps.MpsUnavailable as err:
            said = f"no MPS ({err}): their CUDA contexts take turns on the GPU"
        if clients:  # the daemon numbers the GPUs it sees 0..n-1 for its clients
            clients = {**clients, **mps.client_devices(machine.gpus)[0]}

    def env_for(n):
        shares = {CORES_VARIABLE: str(max(1, machine.cores // n))}
        if on_gpu:
            shares[GPU_SHARE] = str(n)
        return {**clients, **shares}

    return stack, said, env_for


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
    processes = [int(n) for n in args.processes.split(",")]
    if min(processes) < 1:
        raise SystemExit(f"--processes {args.processes}: each a whole number >= 1")
    if args.shared_batch and (len(windows) > 1 or max(processes) > 1):
        raise SystemExit(
            "--shared-batch: one --sim-window and --processes 1 (the batch is built once)"
        )
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
    options = dict(
        task=task.name,
        renderer=args.renderer,
        render_workers=args.render_workers,
        platform=args.platform,
        size=(width, height),
        steps=args.steps,
        latency=args.latency,
        batch_kwargs=batch_kwargs,
    )
    rows = []
    daemon, sharing, env_for = gpu_clients(args, processes)
    with daemon:
        renderer, choice = make_renderer(
            args.renderer,
            workers=args.render_workers,
            platform=args.platform,
            max_size=(width, height),
        )
        with renderer as rp:
            described = (
                f"{args.render_workers} x {rp.gl_info}"
                if choice.backend == "gl"
                else "Warp ray tracer"
            )
            print(
                f"renderer: {described}; backend {args.physics.label}; "
                f"latency {args.latency} s; {args.steps} decisions per episode; {args.size}; "
                f"model server {args.server_processes or 'in this'} process(es)"
                + (f"; several engine processes under {sharing}" if max(processes) > 1 else "")
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
                    print(HEADER)
                    for c, window, n in [
                        (c, w, n) for c in levels for w in windows for n in processes
                    ]:
                        if n > c:
                            print(
                                f"{c:>5} {n:>4} {window:>6.3f}  skipped: "
                                "more processes than episodes",
                            )
                            continue

                        def factory(c=c, window=window):
                            if shared is not None:

                                @contextlib.asynccontextmanager
                                async def reuse():
                                    yield shared

                                return reuse()
                            return task_services(
                                task, c, llm, rp, image=image, sim_window_s=window, **batch_kwargs
                            )

                        if n == 1:
                            totals = await measure(
                                task, c, args.steps, args.latency, factory, seeds
                            )
                            wall = totals["wall_s"]
                        else:
                            totals, wall = await asyncio.to_thread(
                                run_in_processes, options, endpoint, c, n, window, env_for(n)
                            )
                        row = summarize(totals, c, args.steps, args.latency, wall)
                        row.update(
                            concurrency=c,
                            processes=n,
                            process_walls_s=totals.get("process_walls_s"),
                            sim_window_s=window,
                            backend=args.physics.backend,
                            lanes=args.lanes,
                            shared_batch=args.shared_batch,
                            size=args.size,
                            latency_s=args.latency,
                            renderer=described,
                        )
                        rows.append(row)
                        print(row_line(row), flush=True)
                        if args.json:  # after every row: a later row's failure keeps these
                            with open(args.json, "w") as f:
                                json.dump(rows, f, indent=1)
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
        "--processes",
        default="1",
        help="engine processes a round's C episodes are dealt over, a comma list (default 1); "
        "on a GPU they share it under CUDA MPS",
    )
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
    asyncio.run(main_async(args))


if __name__ == "__main__":
    main()
