"""Agent actions per second: the MJX batch against C MuJoCo, measured side by side in one run.

A mixed stream of translations, rotations and gripper commands (IK, waypoint checks and the
ACTION_SECONDS of physics substeps included) on the probe_cube scene (right arm + one cube).

    python benchmarks/sim_throughput.py [--sizes 1,16,256,1024,4096] [--repeats 3] [--json OUT]

For each batch size it prints MJX actions/s (after a compile-and-warm-up step), C MuJoCo in one
thread (mj_step), C MuJoCo through mujoco.rollout on all cores, and the ratios MJX/C.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import numpy as np

from vabench.sim_mjx.cpu import CpuBatch
from vabench.sim_mjx.mjx_batch import SimBatch
from vabench.tasks import get_task

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


def actions_for(n: int, t: int) -> list[dict]:
    """Slot i does stream action (i + t): every call mixes all kinds across the batch."""
    return [STREAM[(i + t) % len(STREAM)] for i in range(n)]


def time_batch(batch, n: int, repeats: int, reset) -> tuple[float, float]:
    """(seconds for the first call, actions/s over `repeats` further calls)."""
    reset(batch)
    t0 = time.perf_counter()
    batch.step(actions_for(n, 0))
    jax.block_until_ready(getattr(batch, "state", None))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for t in range(1, repeats + 1):
        res = batch.step(actions_for(n, t))
    jax.block_until_ready(getattr(batch, "state", None))
    elapsed = time.perf_counter() - t0
    ok = sum(r.planner_success for r in res if r is not None)
    assert ok >= 0.9 * n, f"only {ok}/{n} actions planned: the stream left the workspace"
    return first, n * repeats / elapsed


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", default="1,16,256,1024,4096")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument(
        "--c-max-slots",
        type=int,
        default=64,
        help="C single-thread: slots timed (cost is per slot)",
    )
    p.add_argument(
        "--budget-s", type=float, default=480.0, help="stop starting new sizes after this"
    )
    p.add_argument(
        "--lanes",
        type=int,
        default=None,
        help="MJX lanes (default: SimBatch's; 0 = the whole batch in one vmap)",
    )
    p.add_argument("--json", default=None)
    args = p.parse_args()
    task = get_task("probe_cube")
    model = task.build_model()
    q0 = task.initial_qpos(model, 0)
    threads = os.cpu_count() or 1
    device = jax.devices()[0]
    print(
        f"device: {device.device_kind} ({device.platform}); C threads: {threads}; "
        f"jax {jax.__version__}; "
        f"lanes: {'batch' if args.lanes == 0 else args.lanes or 'default'}"
    )

    def reset(b):
        b.reset(range(b.n_slots), np.broadcast_to(q0, (b.n_slots, model.nq)))

    rows = []
    start = time.perf_counter()
    header = (
        "| batch | MJX actions/s | MJX first call s | C 1-thread actions/s "
        "| C rollout actions/s | MJX/C-1 | MJX/C-rollout |"
    )
    print(header)
    print("|" + "---|" * 7)
    for n in [int(s) for s in args.sizes.split(",")]:
        if time.perf_counter() - start > args.budget_s:
            print(f"(budget reached: sizes from {n} not run)")
            break
        try:
            sb = SimBatch(model, n, lanes=(n if args.lanes == 0 else args.lanes))
            first, mjx_rate = time_batch(sb, sb.n_slots, args.repeats, reset)
            del sb
        except Exception as err:  # out of device memory, most likely
            print(f"| {n} | failed: {type(err).__name__}: {str(err)[:120]} |")
            break
        c1 = CpuBatch(model, min(n, args.c_max_slots))
        _, c1_rate = time_batch(c1, c1.n_slots, args.repeats, reset)
        cr = CpuBatch(model, n, threads=threads)
        _, cr_rate = time_batch(cr, n, args.repeats, reset)
        cr.close()
        row = dict(
            batch=n,
            mjx=mjx_rate,
            mjx_first_s=first,
            c_single=c1_rate,
            c_rollout=cr_rate,
            ratio_single=mjx_rate / c1_rate,
            ratio_rollout=mjx_rate / cr_rate,
        )
        rows.append(row)
        print(
            f"| {n} | {mjx_rate:,.1f} | {first:.1f} | {c1_rate:,.1f} | {cr_rate:,.1f} | "
            f"{row['ratio_single']:.2f} | {row['ratio_rollout']:.2f} |",
            flush=True,
        )
        if args.json:
            with open(args.json, "w") as f:
                json.dump(
                    {"device": str(device.device_kind), "threads": threads, "rows": rows},
                    f,
                    indent=1,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
