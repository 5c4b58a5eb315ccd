"""Seed screening time: 20 seeds of a family in one batch against one seed at a time, measured
side by side in one run, per family.

    python benchmarks/seed_screening.py [--backend mjx|warp|c] [--tasks a,b,...] [--n 20]
                                        [--single K] [--json OUT]

For each family: build the batch (and compile: the first reset and step, timed separately),
then screen candidates 1000 .. 1000+n-1 in one batch (reset + settling gate + expert rollouts,
as `python -m vabench.seeds verify` does), then screen the first K of them one at a time in a
1-slot batch and scale the per-seed mean to n (K = n measures all of them). Prints seconds and
the speed-up, and how many candidates succeeded in each mode (the same seeds must succeed: a
slot's result does not depend on the batch around it).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax

from vabench.tasks import base_tasks, get_task
from vabench.tasks.task_batch import TaskBatch, run_experts

FIRST = 1000


def _warm(tb: TaskBatch) -> float:
    """Compile reset, settle and step for this batch shape; seconds spent."""
    t0 = time.perf_counter()
    tb.reset([0], [FIRST])
    tb.step([{"action": "gripper.close"}])
    tb.evaluate()
    return time.perf_counter() - t0


def measure(name: str, backend: str, n: int, single: int, **kw) -> dict:
    task = get_task(name)
    tb = TaskBatch(task, n, backend=backend, **kw)
    compile_batch = _warm(tb)
    t0 = time.perf_counter()
    eps = run_experts(tb, list(range(FIRST, FIRST + n)))
    batch_s = time.perf_counter() - t0
    compile_single = single_s = 0.0
    singles = []
    if single:
        one = TaskBatch(task, 1, backend=backend, **kw)
        compile_single = _warm(one)
        t0 = time.perf_counter()
        singles = [run_experts(one, [FIRST + i])[0] for i in range(single)]
        single_s = (time.perf_counter() - t0) * n / single
    agree = all(a.success == b.success for a, b in zip(eps, singles, strict=False))
    failed = {
        e.seed: {"end": e.end, "checks": e.last_checks, "last": e.actions[-3:]}
        for e in eps
        if not e.success
    }
    return {
        "task": name,
        "backend": backend,
        "n": n,
        "compile_batch_s": round(compile_batch, 2),
        "batch_s": round(batch_s, 2),
        "compile_single_s": round(compile_single, 2),
        "single_s_for_n": round(single_s, 2),
        "single_measured": single,
        "speedup": round(single_s / batch_s, 2) if single else None,
        "succeeded_batch": sum(e.success for e in eps),
        "succeeded_single": f"{sum(e.success for e in singles)}/{single}",
        "same_outcomes": agree,
        "actions": sum(e.steps for e in eps),
        "failed": failed,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--backend", choices=("mjx", "warp", "c"), default="mjx")
    parser.add_argument("--tasks", default="all", help="comma-separated families or 'all'")
    parser.add_argument("--n", type=int, default=20)
    parser.add_argument("--single", type=int, default=20, help="seeds measured one at a time")
    parser.add_argument("--threads", type=int, default=0, help="C backend: rollout threads")
    parser.add_argument("--json", default=None, help="append one JSON line per family here")
    args = parser.parse_args()
    names = [t.name for t in base_tasks()] if args.tasks == "all" else args.tasks.split(",")
    kw = {"threads": args.threads} if args.backend == "c" and args.threads else {}
    print(f"device: {jax.devices()[0]}  backend: {args.backend}", flush=True)
    print(f"{'task':<30} {'compile':>8} {'batch s':>8} {'1-by-1 s':>9} {'speedup':>8} {'ok':>6}")
    for name in names:
        r = measure(name, args.backend, args.n, min(args.single, args.n), **kw)
        speedup = f"{r['speedup']:>7.2f}x" if r["speedup"] else f"{'-':>8}"
        print(
            f"{name:<30} {r['compile_batch_s']:>8.1f} {r['batch_s']:>8.1f} "
            f"{r['single_s_for_n']:>9.1f} {speedup} {r['succeeded_batch']:>3}/{args.n}",
            flush=True,
        )
        for seed, why in r["failed"].items():
            print(f"    seed {seed}: {why['end']}; {why['checks']}", flush=True)
        if args.json:
            with open(args.json, "a") as f:
                f.write(json.dumps({**r, "device": str(jax.devices()[0])}) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
