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
processes.

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
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


STAGES = ("sim_busy_s", "sim_calls", "sim_items", "render_busy_s", "render_calls", "render_items")


async def measure(task, n_episodes, steps, latency, svc_factory, seeds, ready=None, on_totals=None):
    """The totals of one timed round of `n_episodes` (after an untimed warm-up episode; then
    `ready()`, when given, is awaited before the clock starts: the processes' start line;
    `on_totals(totals)` is told them before the services close, which takes a while)."""
    from vabench.agent.engine import EpisodeSpec, run_episodes

    def stages(svc):
        s, r = svc.sim.stats, svc.render.stats
        return (s.busy_s, s.calls, s.items, r.busy_s, r.calls, r.items)

    async with svc_factory() as svc:
        warm = [EpisodeSpec(task.name, seeds[0], "local", step_budget=1)]
        await run_episodes(warm, svc)  # compile and warm the workers, untimed
        if ready is not None:
            await ready()
        before = stages(svc)
        specs = [
            EpisodeSpec(task.name, seeds[i % len(seeds)], "local", step_budget=steps)
            for i in range(n_episodes)
        ]
        t0, cpu0, loop0 = time.perf_counter(), time.process_time(), time.thread_time()
        results = await run_episodes(specs, svc)
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        loop_cpu = time.thread_time() - loop0  # this coroutine runs on the event loop's thread
        after = stages(svc)
        bad = [r for r in results if not r.scored]
        totals = dict(
            wall_s=wall,
            cpu_s=cpu,
            loop_cpu_s=loop_cpu,
            decisions=sum(r.steps_used for r in results),
            errors=len(bad),
            error_examples=[r.error for r in bad[:2]],
            **{k: a - b for k, a, b in zip(STAGES, after, before, strict=True)},
        )
        if on_totals is not None:
            on_totals(totals)
    return totals


def summarize(totals, n_episodes, steps, latency, wall):
    """A row from the totals of one or more engine processes and the round's wall time."""
    decisions = max(totals["decisions"], 1)
    return dict(
        episodes=n_episodes,
        wall_s=wall,
        ideal_s=steps * latency,
        decisions=totals["decisions"],
        episodes_per_hour=n_episodes / wall * 3600,
        ideal_episodes_per_hour=n_episodes / (steps * latency) * 3600,
        ratio=steps * latency / wall,
        overhead_per_decision_s=wall / steps - latency,
        engine_cpu_per_decision_s=totals["cpu_s"] / decisions,
        loop_cpu_per_decision_s=totals["loop_cpu_s"] / decisions,
        sim_busy_per_decision_s=totals["sim_busy_s"] / decisions,
        sim_calls=totals["sim_calls"],
        sim_mean_batch=totals["sim_items"] / max(totals["sim_calls"], 1),
        render_busy_per_image_s=totals["render_busy_s"] / max(totals["render_items"], 1),
        render_calls=totals["render_calls"],
        render_mean_batch=totals["render_items"] / max(totals["render_calls"], 1),
        errors=totals["errors"],
        error_examples=totals["error_examples"],
    )


def shares(total, n):
    """`total` episodes dealt over `n` processes as evenly as they go."""
    return [total // n + (1 if i < total % n else 0) for i in range(n)]


START_TIMEOUT_S = 600.0
"""How long the engine processes may take to start, compile and warm up (a fresh machine's
Warp kernels included)."""


def run_in_processes(options, endpoint, n_episodes, n_processes, window):
    """One timed round of `n_episodes` dealt over `n_processes` engine processes (each its own
    batch, renderer and model client, as the sweep's `processes` executor runs them), started
    together once each has warmed up: the wall time is the parent's, from that start to the
    last process's totals. Returns the summed totals and the wall time."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    start = ctx.Barrier(n_processes + 1)
    replies = ctx.SimpleQueue()
    parts = [n for n in shares(n_episodes, n_processes) if n]
    if len(parts) < n_processes:
        raise SystemExit(
            f"--processes {n_processes}: more processes than the {n_episodes} episodes"
        )
    procs = [
        ctx.Process(
            target=_engine_process,
            args=(options, endpoint, part, window, offset, start, replies),
            name=f"engine-{i}",  # not daemonic: a GL renderer starts processes of its own
        )
        for i, (part, offset) in enumerate(
            zip(parts, [sum(parts[:i]) for i in range(len(parts))], strict=True)
        )
    ]
    try:
        for proc in procs:
            proc.start()
        got, wall = _timed_replies(procs, start, replies)
    except BaseException:
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
        raise
    for proc in procs:
        proc.join(timeout=60)
    failed = [g for g in got if isinstance(g, str)]
    if failed:
        raise SystemExit(f"an engine process failed: {failed[0]}")
    totals = {k: sum(g[k] for g in got) for k in ("cpu_s", "loop_cpu_s", "decisions", "errors")}
    totals.update({k: sum(g[k] for g in got) for k in STAGES})
    totals["error_examples"] = [e for g in got for e in g["error_examples"]][:2]
    totals["process_walls_s"] = [round(g["wall_s"], 2) for g in got]
    return totals, wall


def _timed_replies(procs, start, replies):
    """Start the processes' round together; their totals and the wall time until the last."""
    try:
        start.wait(timeout=START_TIMEOUT_S)
    except threading.BrokenBarrierError:
        for proc in procs:
            proc.join(timeout=10)
        why = []
        while not replies.empty():
            why.append(replies.get())
        reason = next((w for w in why if isinstance(w, str)), "timed out")
        raise SystemExit(f"the engine processes did not start: {reason}") from None
    t0 = time.perf_counter()
    got: list = []
    while len(got) < len(procs):  # polled: a process that dies without a word ends the wait
        if not replies.empty():
            got.append(replies.get())
            continue
        if sum(p.exitcode is not None for p in procs) > len(got):
            time.sleep(0.5)  # a process that has ended: its totals may still be in the pipe
            if replies.empty():
                raise SystemExit("an engine process ended without its totals (see its output)")
            continue
        time.sleep(0.005)
    return got, time.perf_counter() - t0


def _engine_process(options, endpoint, n_episodes, window, offset, start, replies):
    """One engine process of `run_in_processes` (spawned: a module-level function)."""
    try:  # the totals go to the parent as soon as they are measured (`on_totals`)
        asyncio.run(_engine_async(options, endpoint, n_episodes, window, offset, start, replies))
    except BaseException as err:  # the parent learns of it instead of waiting forever
        start.abort()
        replies.put(f"{type(err).__name__}: {err}")


async def _engine_async(options, endpoint, n_episodes, window, offset, start, replies):
    from vabench.agent.services import task_services
    from vabench.llm_pool.pool import LLMPool
    from vabench.render.backends import make_renderer
    from vabench.render.worker import ImageSettings
    from vabench.tasks import get_task
    from vabench.tasks.manifests import verified_seeds

    task = get_task(options["task"])
    seeds = verified_seeds(task.name)
    seeds = seeds[offset % len(seeds) :] + seeds[: offset % len(seeds)]
    width, height = options["size"]
    renderer, _ = make_renderer(
        options["renderer"],
        workers=options["render_workers"],
        platform=options["platform"],
        max_size=(width, height),
    )
    with renderer as rp:
        async with LLMPool([endpoint]) as llm:

            def factory():
                return task_services(
                    task,
                    n_episodes,
                    llm,
                    rp,
                    image=ImageSettings(width, height, 95),
                    sim_window_s=window,
                    **options["batch_kwargs"],
                )

            return await measure(
                task,
                n_episodes,
                options["steps"],
                options["latency"],
                factory,
                seeds,
                ready=lambda: asyncio.to_thread(start.wait, START_TIMEOUT_S),
                on_totals=replies.put,
            )


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
    """CUDA MPS for the rows of several engine processes on a GPU (`vabench.sweep.mps`, as the
    sweep's `processes` executor starts it): its variables are put in this process's
    environment, so that the engine processes and this one's renderer are its clients."""
    import contextlib

    from vabench.sweep import mps

    stack = contextlib.ExitStack()
    if args.renderer != "warp" or max(processes) < 2:
        return stack, "no MPS"
    try:
        env = stack.enter_context(mps.private_daemon())
    except mps.MpsUnavailable as err:
        return stack, f"no MPS ({err}): the processes take turns on the GPU"
    os.environ.update(env)
    return stack, "CUDA MPS"


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
    daemon, sharing = gpu_clients(args, processes)
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
                                run_in_processes, options, endpoint, c, n, window
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
    rows = asyncio.run(main_async(args))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
