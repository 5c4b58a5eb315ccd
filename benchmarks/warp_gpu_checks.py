"""Checks of the Warp backend that only a GPU can make, printed as one report.

    python benchmarks/warp_gpu_checks.py [--task place_single_cube] [--slots 256] [--json OUT]

- graph capture: seconds to capture and instantiate the action graph, then one launch;
- batch independence on the GPU: a slot alone vs the same slot among busy neighbours in a
  bigger batch, with MuJoCo Warp's default (atomic) orderings and with `deterministic`: are
  they bit-identical, and if not how far apart (GC, mm) after a few actions;
- run-to-run: the same batch twice from the same state;
- frozen idle slots and the overflow error, as on the CPU (tests/test_warp_batch.py);
- the expert of the task on its first verified seeds, on Warp.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from vabench.sim_mjx.interface import STATE_FIELDS
from vabench.sim_mjx.warp.batch import WarpBatch
from vabench.tasks import get_task
from vabench.tasks.manifests import verified_seeds
from vabench.tasks.task_batch import TaskBatch, run_experts

ACTIONS = [
    {"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 40},
    {"action": "gripper.rotate_local", "axis": "rz", "sign": "+", "angle_deg": 20},
    {"action": "gripper.close"},
    {"action": "gripper.move_world", "axis": "x", "sign": "+", "distance_mm": 30},
]
NEIGHBOUR = {"action": "gripper.move_world", "axis": "y", "sign": "+", "distance_mm": 50}


def gc_gap_mm(a: WarpBatch, i: int, b: WarpBatch, j: int) -> float:
    return 1000 * float(np.max(np.abs(a.proprio().gc[i] - b.proprio().gc[j])))


def equal(a: dict, b: dict) -> bool:
    return all(np.array_equal(a[f], b[f]) for f in STATE_FIELDS)


def gaps(a: dict, b: dict) -> dict:
    """Largest absolute difference per state field (0 where bit-identical)."""
    return {
        f: float(np.max(np.abs(a[f].astype(float) - b[f].astype(float)), initial=0.0))
        for f in STATE_FIELDS
    }


def independence(model, q0, slots: int, deterministic: bool) -> dict:
    alone = WarpBatch(model, 1, deterministic=deterministic)
    crowd = WarpBatch(model, slots, deterministic=deterministic)
    for b in (alone, crowd):
        b.reset(range(b.n_slots), np.broadcast_to(q0, (b.n_slots, len(q0))), settle_steps=100)
    k = slots - 1
    for action in ACTIONS:
        alone.step([action])
        crowd.step([NEIGHBOUR] * k + [action])
    out = {
        "deterministic": deterministic,
        "bit_identical": equal(alone.get_state([0]), crowd.get_state([k])),
        "gc_gap_mm": gc_gap_mm(alone, 0, crowd, k),
        "field_gaps": gaps(alone.get_state([0]), crowd.get_state([k])),
    }
    again = WarpBatch(model, slots, deterministic=deterministic)
    again.reset(range(slots), np.broadcast_to(q0, (slots, len(q0))), settle_steps=100)
    for action in ACTIONS:
        again.step([NEIGHBOUR] * k + [action])
    everyone = list(range(slots))
    out["run_to_run_identical"] = equal(again.get_state(everyone), crowd.get_state(everyone))
    out["run_to_run_gaps"] = gaps(again.get_state(everyone), crowd.get_state(everyone))
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="place_single_cube")
    p.add_argument("--slots", type=int, default=256)
    p.add_argument("--json", default=None)
    p.add_argument("--only-independence", action="store_true")
    args = p.parse_args()
    task = get_task(args.task)
    model = task.build_model()
    seeds = verified_seeds(task.name)
    q0 = task.initial_qpos(model, task.sample(seeds[0]))
    report: dict = {"task": task.name, "slots": args.slots}
    if args.only_independence:
        for det in (False, True):
            print(json.dumps(independence(model, q0, args.slots, det)), flush=True)
        return 0

    t0 = time.perf_counter()
    b = WarpBatch(model, args.slots)
    report["construct_s"] = time.perf_counter() - t0
    b.reset(range(args.slots), np.broadcast_to(q0, (args.slots, model.nq)))
    t0 = time.perf_counter()
    res = b.step([ACTIONS[0]] * args.slots)
    report["first_action_s"] = time.perf_counter() - t0  # capture + instantiate + launch
    t0 = time.perf_counter()
    res = b.step([ACTIONS[1]] * args.slots)
    report["second_action_s"] = time.perf_counter() - t0
    report["planned"] = sum(bool(r and r.planner_success) for r in res)
    report["memory_kib_per_slot"] = b.memory_bytes() / args.slots / 1024
    print(json.dumps(report), flush=True)

    before = b.get_state([1])
    b.step([ACTIONS[2]] + [None] * (args.slots - 1))
    report["idle_frozen"] = equal(before, b.get_state([1]))

    small = WarpBatch(model, 2, nconmax=1)
    small.reset([0, 1], np.broadcast_to(q0, (2, model.nq)), settle_steps=10)
    res = small.step([ACTIONS[0], None])
    report["overflow_error"] = res[0].infrastructure_error
    print(json.dumps(report), flush=True)

    for det in (False, True):
        report[f"independence_det{int(det)}"] = independence(model, q0, args.slots, det)
        print(json.dumps(report[f"independence_det{int(det)}"]), flush=True)

    tb = TaskBatch(task, 20, backend="mjx", impl="warp")
    t0 = time.perf_counter()
    eps = run_experts(tb, seeds[:20])
    report["expert"] = {
        "solved": sum(e.success for e in eps),
        "of": len(eps),
        "seconds": time.perf_counter() - t0,
        "failures": {e.seed: e.end for e in eps if not e.success},
    }
    print(json.dumps(report["expert"]), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
