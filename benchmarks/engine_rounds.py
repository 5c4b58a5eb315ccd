"""One timed round of the engine benchmark (benchmarks/engine.py): C episodes of one task in
one engine process (`measure`), or dealt over several (`run_in_processes`), and the row made
of its totals (`summarize`)."""

from __future__ import annotations

import asyncio
import multiprocessing
import sys
import threading
import time

from vabench.children import started_with

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
JOIN_TIMEOUT_S = 60.0
"""How long an engine process may take to close its services after its totals."""


def run_in_processes(options, endpoint, n_episodes, n_processes, window, env=None):
    """One timed round of `n_episodes` dealt over `n_processes` engine processes (each its own
    batch, renderer and model client, as the sweep's `processes` executor runs them; `env`: the
    variables they start with, e.g. those of an MPS daemon's clients), started together once
    each has warmed up. The wall time is this process's, from that start to the last process's
    totals; the CPU totals add this process's own over that time (the embedded server's, where
    it runs here). Returns the summed totals and the wall time."""
    ctx = multiprocessing.get_context("spawn")
    parts = shares(n_episodes, n_processes)
    if not all(parts):
        raise SystemExit(
            f"--processes {n_processes}: more processes than the {n_episodes} episodes"
        )
    start = ctx.Barrier(n_processes + 1)
    replies = ctx.SimpleQueue()
    offsets = [sum(parts[:i]) for i in range(n_processes)]
    procs = [
        ctx.Process(
            target=_engine_process,
            args=(i, options, endpoint, part, window, offset, start, replies),
            name=f"engine-{i}",  # not daemonic: a GL renderer starts processes of its own
        )
        for i, (part, offset) in enumerate(zip(parts, offsets, strict=True))
    ]
    measured = False
    try:
        with started_with(env or {}):  # a spawned process starts with this environment
            for proc in procs:
                proc.start()
        got, wall, own_cpu = _timed_replies(procs, start, replies)
        measured = True
    finally:  # measured: each closes its services; else the others' rounds are moot
        for proc in procs:
            if measured:
                proc.join(timeout=JOIN_TIMEOUT_S)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=10)
    totals = {k: sum(g[k] for g in got) for k in ("cpu_s", "loop_cpu_s", "decisions", "errors")}
    totals["cpu_s"] += own_cpu
    totals.update({k: sum(g[k] for g in got) for k in STAGES})
    totals["error_examples"] = [e for g in got for e in g["error_examples"]][:2]
    totals["process_walls_s"] = [round(g["wall_s"], 2) for g in got]
    return totals, wall


def _timed_replies(procs, start, replies):
    """Start the processes' round together; their totals (in process order), the wall time
    until the last and this process's CPU time over it. A process that fails or dies, before
    the start or after, ends the round with its reason (SystemExit)."""
    started = threading.Event()

    def watch():  # a process that dies before the start would leave the others waiting
        while not started.wait(0.2):
            if any(p.exitcode is not None for p in procs):
                start.abort()
                return

    threading.Thread(target=watch, name="engine-start-watch", daemon=True).start()
    try:
        start.wait(timeout=START_TIMEOUT_S)
    except threading.BrokenBarrierError:
        started.set()
        time.sleep(0.5)  # a failing process's reason may still be on its way
        said = _drain(replies)
        reason = next((p for _, kind, p in said if kind == "error"), None)
        dead = [f"{p.name} exited {p.exitcode}" for p in procs if p.exitcode is not None]
        raise SystemExit(
            f"the engine processes did not start: {reason or ', '.join(dead) or 'timed out'}"
        ) from None
    started.set()
    t0, cpu0 = time.perf_counter(), time.process_time()
    totals: dict[int, dict] = {}
    while len(totals) < len(procs):
        if not replies.empty():
            index, kind, payload = replies.get()
            if kind == "error":
                raise SystemExit(f"engine process {index} failed: {payload}")
            totals[index] = payload
            continue
        lost = [p.name for i, p in enumerate(procs) if p.exitcode is not None and i not in totals]
        if lost:
            time.sleep(0.5)  # a process that has ended: its totals may still be in the pipe
            if replies.empty():
                raise SystemExit(f"{lost[0]} ended without its totals (see its output)")
            continue
        time.sleep(0.005)
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    return [totals[i] for i in range(len(procs))], wall, cpu


def _drain(replies):
    said = []
    while not replies.empty():
        said.append(replies.get())
    return said


def _engine_process(index, options, endpoint, n_episodes, window, offset, start, replies):
    """One engine process of `run_in_processes` (spawned: a module-level function). Its totals
    go to the parent as soon as they are measured, before its services close."""
    sent = []

    def send(totals):
        replies.put((index, "totals", totals))
        sent.append(True)

    try:
        asyncio.run(_engine_async(options, endpoint, n_episodes, window, offset, start, send))
    except BaseException as err:
        if sent:  # the round is measured: a failure while closing is only reported
            print(f"engine process {index}, after its totals: {err!r}", file=sys.stderr)
            return
        start.abort()  # the parent and the others learn of it instead of waiting
        replies.put((index, "error", f"{type(err).__name__}: {err}"))


async def _engine_async(options, endpoint, n_episodes, window, offset, start, send):
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
                on_totals=send,
            )
