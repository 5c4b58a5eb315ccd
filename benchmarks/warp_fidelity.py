"""Fidelity of the Warp backend against C MuJoCo, family by family, over the verified seeds.

    python benchmarks/warp_fidelity.py [--tasks all|T1,T2] [--n 20] [--json OUT] [--md OUT]

For every family and its first `--n` verified seeds (one batch per backend):
1. the expert on C MuJoCo (the backend the seeds were verified on), recording its actions;
2. the expert on MuJoCo Warp, closed loop: does it solve every retained seed there too?
3. C's action lists replayed open loop on both backends in lockstep: after every action, the
   distance between the finger centres (GC) of the two backends, and between the objects'
   positions. The target is GC within 2 mm after every action.

Prints a Markdown table (solved on C / on Warp, worst GC and object deviation with the seed and
step where it happened) and writes JSON rows. Long: run it on a GPU host. The Warp device is
`VABENCH_WARP_DEVICE` (default the first GPU); `VABENCH_WARP_DEVICE=cpu` runs the same MuJoCo Warp
kernels on Warp's CPU backend, one thread (the basket's 20 seeds: 15 minutes on a 2-core
machine), for a family the GPU's time did not reach; every row names its device.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from vabench.sim_mjx.controller import ACTION_ENDS
from vabench.sim_mjx.reset_cache import SettledCache
from vabench.sim_mjx.warp.device import warp_device
from vabench.tasks import benchmark_tasks, get_task
from vabench.tasks.manifests import verified_seeds
from vabench.tasks.task_batch import TaskBatch, run_experts

GC_TOLERANCE_MM = 2.0


def replay_lockstep(
    batches: dict[str, TaskBatch], seeds: list[int], scripts: list[list[dict]]
) -> dict[str, np.ndarray]:
    """Replay each seed's action list on every batch in lockstep; per seed the worst GC and
    object deviation (mm) from the first batch, and the step of the worst GC deviation."""
    for tb in batches.values():
        tb.reset(range(len(seeds)), seeds)
    names = list(batches)
    ref, other = batches[names[0]], batches[names[1]]
    worst_gc = np.zeros(len(seeds))
    worst_obj = np.zeros(len(seeds))
    at_step = np.zeros(len(seeds), int)
    for step in range(max(len(s) for s in scripts)):
        actions = [s[step] if step < len(s) else None for s in scripts]
        for tb in batches.values():
            tb.step(actions + [None] * (tb.n_slots - len(actions)))
        pa, pb = ref.batch.proprio(), other.batch.proprio()
        qa, qb = ref.batch.qpos(), other.batch.qpos()
        for i, action in enumerate(actions):
            if action is None:
                continue
            gc = 1000 * float(np.max(np.linalg.norm(pa.gc[i] - pb.gc[i], axis=-1)))
            obj = max(
                (1000 * float(np.linalg.norm(qa[i, a : a + 3] - qb[i, a : a + 3])))
                for a in ref.ix.adr.values()
            )
            if gc > worst_gc[i]:
                worst_gc[i], at_step[i] = gc, step + 1
            worst_obj[i] = max(worst_obj[i], obj)
    return {"gc_mm": worst_gc, "object_mm": worst_obj, "step": at_step}


def stage(name: str, what: str, t0: float) -> None:
    """A progress line: a family of many actions (the basket) runs for minutes."""
    print(f"  {name}: {what} done at {time.perf_counter() - t0:.0f} s", flush=True)


def family_row(name: str, n: int, cache: SettledCache, action_end: str = "fixed") -> dict:
    t0 = time.perf_counter()
    task = get_task(name)
    seeds = verified_seeds(name)[:n]
    # C slots on threads (one per seed, up to the cores): the basket's 20 experts took 107 s
    # on one thread of the H100 host, more than half of the call's budget.
    threads = min(len(seeds), len(os.sched_getaffinity(0)))
    c = TaskBatch(
        task, len(seeds), backend="c", cache=cache, threads=threads, action_end=action_end
    )
    w = TaskBatch(task, len(seeds), backend="mjx", impl="warp", cache=cache, action_end=action_end)
    stage(name, "built both batches", t0)
    on_c = run_experts(c, seeds)
    stage(name, f"C experts ({sum(ep.steps for ep in on_c)} actions)", t0)
    on_w = run_experts(w, seeds)
    stage(name, f"Warp experts ({sum(ep.steps for ep in on_w)} actions)", t0)
    scripts = [[a["action"] for a in ep.actions] for ep in on_c]
    dev = replay_lockstep({"c": c, "warp": w}, seeds, scripts)
    stage(name, "lockstep replay", t0)
    worst = int(np.argmax(dev["gc_mm"]))
    failed = [ep.seed for ep in on_w if not ep.success]
    row = {
        "task": name,
        "warp_device": warp_device(),
        "seeds": len(seeds),
        "solved_c": sum(ep.success for ep in on_c),
        "solved_warp": sum(ep.success for ep in on_w),
        "warp_failures": {ep.seed: ep.end for ep in on_w if not ep.success},
        "gc_max_mm": float(dev["gc_mm"].max()),
        "gc_median_mm": float(np.median(dev["gc_mm"])),
        "gc_worst_seed": seeds[worst],
        "gc_worst_step": int(dev["step"][worst]),
        "gc_within_tol": int(np.sum(dev["gc_mm"] <= GC_TOLERANCE_MM)),
        "object_max_mm": float(dev["object_mm"].max()),
        "object_median_mm": float(np.median(dev["object_mm"])),
        "steps_c": sum(ep.steps for ep in on_c),
        "steps_warp": sum(ep.steps for ep in on_w),
        "seconds": time.perf_counter() - t0,
    }
    if failed:
        row["note"] = f"Warp expert failed seeds {failed}"
    for tb in (c, w):
        tb.batch.close()
    return row


def markdown(rows: list[dict]) -> str:
    lines = [
        "| family | solved C | solved Warp | GC max mm (seed, step) | GC median mm | "
        f"seeds with GC <= {GC_TOLERANCE_MM:g} mm | object max mm | object median mm |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['task']} | {r['solved_c']}/{r['seeds']} | {r['solved_warp']}/{r['seeds']} | "
            f"{r['gc_max_mm']:.2f} ({r['gc_worst_seed']}, {r['gc_worst_step']}) | "
            f"{r['gc_median_mm']:.2f} | {r['gc_within_tol']}/{r['seeds']} | "
            f"{r['object_max_mm']:.1f} | {r['object_median_mm']:.2f} |"
        )
    solved = sum(r["solved_warp"] == r["seeds"] for r in rows)
    lines.append(f"\nFamilies whose every seed the Warp expert solves: {solved}/{len(rows)}")
    devices = sorted({str(r.get("warp_device", "?")) for r in rows})
    lines.append(f"Warp device: {', '.join(devices)}")
    return "\n".join(lines)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", default="all")
    p.add_argument("--n", type=int, default=20)
    p.add_argument("--json", default=None)
    p.add_argument("--md", default=None)
    p.add_argument("--budget-s", type=float, default=1e9, help="stop starting new families")
    p.add_argument(
        "--action-end", default="fixed", choices=ACTION_ENDS, help="simulator.action_end"
    )
    args = p.parse_args()
    names = [t.name for t in benchmark_tasks()] if args.tasks == "all" else args.tasks.split(",")
    cache = SettledCache.default()
    rows, start = [], time.perf_counter()
    for name in names:
        if time.perf_counter() - start > args.budget_s:
            print(f"(budget reached: {name} and later not run)", flush=True)
            break
        try:
            row = family_row(name, args.n, cache, args.action_end)
        except Exception as err:  # report the family and go on with the others
            row = {"task": name, "error": f"{type(err).__name__}: {err}"}
            print(f"{name}: {row['error']}", flush=True)
        else:
            print(
                f"{name}: solved C {row['solved_c']}/{row['seeds']}, Warp "
                f"{row['solved_warp']}/{row['seeds']}; GC max {row['gc_max_mm']:.2f} mm, "
                f"object max {row['object_max_mm']:.1f} mm ({row['seconds']:.0f} s)",
                flush=True,
            )
        rows.append(row)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
    table = markdown([r for r in rows if "error" not in r])
    print(table)
    if args.md:
        Path(args.md).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
