"""Agent actions per second: MuJoCo Warp, C MuJoCo on all cores and MJX-JAX, side by side.

    python benchmarks/sim_throughput.py [--tasks place_single_cube,lift_pot]
        [--sizes 256,1024,8192] [--backends warp,c,jax] [--repeats 3] [--json OUT]

One action = plan (25 closed-form IK waypoints with table/limit checks) + ACTION_SECONDS of
physics (200 substeps at 4 ms) for every slot of the batch, from a mixed stream of
translations, local rotations and gripper commands (each slot at another point of the stream,
so every call mixes all kinds). Commands go in as arrays (`BatchBase.step_rows`, the bulk path);
"warp+encode" also times `step` with one protocol dict per slot (validation and encoding
included). C MuJoCo runs through `mujoco.rollout` on every core; "C-1" is one thread on up to
`--c1-max-slots` slots. Each row is measured in one run; the ratios are the point.

A second table times a reset of `--reset-slots` slots of `--reset-task` from the settled-state
cache (seeds cycling over the task's verified seeds), against settling them, and reports the
Warp batch's GPU memory per slot.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from vabench.protocol import parse_robot_action
from vabench.sim_mjx.actions import CommandRows, encode
from vabench.sim_mjx.backends import make_batch
from vabench.sim_mjx.interface import BatchBase
from vabench.sim_mjx.reset_cache import SettledCache
from vabench.sim_mjx.warp.device import warp_device, warp_problem
from vabench.tasks import get_task
from vabench.tasks.manifests import manifest_path, verified_seeds
from vabench.tasks.task_batch import TaskBatch

# Each pair returns the arm near where it started, so a long stream stays in the workspace.
STREAM = [
    {"action": "gripper.move_world", "axis": "x", "sign": "+", "distance_mm": 40},
    {"action": "gripper.rotate_local", "axis": "rz", "sign": "+", "angle_deg": 20},
    {"action": "gripper.close"},
    {"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 60},
    {"action": "gripper.rotate_local", "axis": "rx", "sign": "-", "angle_deg": 30},
    {"action": "gripper.move_world", "axis": "x", "sign": "-", "distance_mm": 40},
    {"action": "gripper.open"},
    {"action": "gripper.rotate_local", "axis": "rz", "sign": "-", "angle_deg": 20},
    {"action": "gripper.move_world", "axis": "z", "sign": "+", "distance_mm": 60},
    {"action": "gripper.rotate_local", "axis": "rx", "sign": "+", "angle_deg": 30},
]
BACKENDS = {"warp": ("mjx", "warp"), "jax": ("mjx", "jax"), "c": ("c", "auto")}


def stream_for(arms: tuple[str, ...]) -> list[dict]:
    """The stream for a scene: dual-arm scenes name the arm (the right one moves)."""
    return STREAM if len(arms) == 1 else [{**a, "arm": "right"} for a in STREAM]


def stream_rows(arms: tuple[str, ...], n: int, t: int) -> CommandRows:
    """Slot i does stream action (i + t), encoded in bulk from the stream's own rows."""
    template = CommandRows.idle(len(STREAM), len(arms))
    for k, raw in enumerate(stream_for(arms)):
        encode(parse_robot_action(raw, arms), arms, template, k)
    pick = (np.arange(n) + t) % len(STREAM)
    return CommandRows(
        template.active[pick], template.delta[pick], template.rotvec[pick], template.grip[pick]
    )


def stream_dicts(arms: tuple[str, ...], n: int, t: int) -> list[dict]:
    stream = stream_for(arms)
    return [stream[(i + t) % len(stream)] for i in range(n)]


def time_batch(
    batch: BatchBase, q0: np.ndarray, n: int, repeats: int, encoded: bool
) -> tuple[float, float]:
    """(seconds for the first call, actions/s over `repeats` further calls)."""
    batch.reset(range(batch.n_slots), np.broadcast_to(q0, (batch.n_slots, len(q0))))

    def call(t: int) -> int:
        if encoded:
            info = batch.step_rows(stream_rows(batch.arms, batch.n_slots, t))
            return int(np.sum(info.planner_success[:n]))
        res = batch.step(stream_dicts(batch.arms, n, t))
        return sum(bool(r and r.planner_success) for r in res)

    t0 = time.perf_counter()
    call(0)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for t in range(1, repeats + 1):
        ok = call(t)
    elapsed = time.perf_counter() - t0
    if ok < 0.9 * n:
        raise RuntimeError(f"only {ok}/{n} actions planned: the stream left the workspace")
    return first, n * repeats / elapsed


def throughput(args: argparse.Namespace, threads: int) -> list[dict]:
    rows: list[dict] = []
    start = time.perf_counter()
    header = "| task | batch | backend | actions/s | first call s | vs C (all cores) |"
    print(header)
    print("|" + "---|" * 6, flush=True)
    for task_name in args.tasks.split(","):
        task = get_task(task_name)
        models = task.build_models()
        seed = verified_seeds(task_name)[0] if manifest_path(task_name).exists() else 0
        q0 = task.initial_qpos(models[0], task.sample(seed))
        for n in [int(s) for s in args.sizes.split(",")]:
            if time.perf_counter() - start > args.budget_s:
                print(f"(budget reached: {task_name} from batch {n} not run)")
                break
            found: dict[str, float] = {}
            for name in args.backends.split(","):
                if name == "jax" and n > args.jax_max_slots:
                    continue
                backend, impl = BACKENDS[name]
                variants: list[tuple[str, bool, dict]] = []
                if name == "warp":
                    loops = args.loops.split(",")
                    for loop in loops:
                        label = "warp" if len(loops) == 1 else f"warp/{loop}"
                        variants.append((label, True, {"loop": loop}))
                    if args.encode:
                        variants.append(("warp+encode", False, {"loop": loops[0]}))
                elif name == "c":
                    variants += [("c", True, {"threads": threads}), ("C-1", True, {})]
                else:
                    variants.append((name, True, {}))
                for label, encoded, kw in variants:
                    size = min(n, args.c1_max_slots) if label == "C-1" else n
                    try:
                        batch = make_batch(models, size, backend, impl, **kw)
                        try:
                            first, rate = time_batch(batch, q0, size, args.repeats, encoded)
                        finally:
                            batch.close()
                    except Exception as err:  # out of memory, a capture Warp refuses: go on
                        print(f"| {task_name} | {size} | {label} | failed: {err!r:.300} |")
                        continue
                    found[label] = rate
                    rows.append(
                        dict(task=task_name, batch=size, backend=label, rate=rate, first_s=first)
                    )
            for row in rows[len(rows) - len(found) :]:  # this size, once C is measured
                ratio = "-"
                if "c" in found:
                    row["vs_c"] = row["rate"] / found["c"]
                    ratio = f"{row['vs_c']:.2f}"
                print(
                    f"| {task_name} | {row['batch']} | {row['backend']} | "
                    f"{row['rate']:,.0f} | {row['first_s']:.1f} | {ratio} |",
                    flush=True,
                )
    return rows


def reset_timing(args: argparse.Namespace) -> dict:
    """Reset of many slots from the settled-state cache vs settling them (Warp)."""
    task = get_task(args.reset_task)
    seeds = verified_seeds(task.name)
    n = args.reset_slots
    slot_seeds = [seeds[i % len(seeds)] for i in range(n)]
    root = Path(tempfile.mkdtemp(prefix="vabench-settled-"))
    tb = TaskBatch(task, n, backend="mjx", impl="warp", cache=SettledCache(root))
    t0 = time.perf_counter()
    tb.reset(range(n), slot_seeds)  # unique seeds settle once each, the rest hit memory
    settle_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    tb.reset(range(n), slot_seeds)
    memory_s = time.perf_counter() - t0
    tb.cache = SettledCache(root)  # a new process: entries come from disk
    t0 = time.perf_counter()
    tb.reset(range(n), slot_seeds)
    disk_s = time.perf_counter() - t0
    mem = tb.batch.memory_bytes() if hasattr(tb.batch, "memory_bytes") else 0
    out = dict(
        task=task.name,
        slots=n,
        unique_seeds=len(set(slot_seeds)),
        first_reset_s=settle_s,
        cached_reset_memory_s=memory_s,
        cached_reset_disk_s=disk_s,
        gpu_bytes_per_slot=mem / n,
    )
    print(
        f"\nreset of {n} slots of {task.name} ({len(set(slot_seeds))} seeds): settle "
        f"{settle_s:.2f} s; from the cache {1000 * memory_s:.1f} ms (memory), "
        f"{1000 * disk_s:.1f} ms (disk); GPU memory {mem / n / 1024:.0f} KiB per slot",
        flush=True,
    )
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", default="place_single_cube,lift_pot")
    p.add_argument("--sizes", default="256,1024,8192")
    p.add_argument("--backends", default="warp,c,jax")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--loops", default="unrolled", help="Warp substep loops (see LOOPS)")
    p.add_argument("--encode", action="store_true", help="also time Warp through step(dicts)")
    p.add_argument("--c1-max-slots", type=int, default=32, help="C one thread: slots timed")
    p.add_argument("--jax-max-slots", type=int, default=1024, help="MJX-JAX: largest batch")
    p.add_argument("--reset-task", default="place_single_cube")
    p.add_argument("--reset-slots", type=int, default=1024, help="0: skip the reset timing")
    p.add_argument("--budget-s", type=float, default=540.0, help="stop starting new sizes")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    threads = os.cpu_count() or 1
    problem = warp_problem()
    if problem and "warp" in args.backends:
        print(f"Warp not measured: {problem}")
        args.backends = ",".join(b for b in args.backends.split(",") if b != "warp")
        args.reset_slots = 0
    gpu = "-"
    if "warp" in args.backends:
        import warp as wp

        gpu = wp.get_device(warp_device()).name
    print(f"GPU: {gpu}; C threads: {threads}; backends: {args.backends}")
    doc: dict = {"gpu": gpu, "threads": threads, "rows": throughput(args, threads)}
    if args.reset_slots:
        doc["reset"] = reset_timing(args)
    if args.json:
        Path(args.json).write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
