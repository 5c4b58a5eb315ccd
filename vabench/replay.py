"""Evaluator CLI: execute a list of model-facing actions on one task seed and print every step.

    python -m vabench.replay --task probe_cube --seed 3 --actions actions.json --json

The actions file holds a JSON list of action objects exactly as the model emits them (FACTS.md).
The output is one JSON document {"task", "seed", "steps": [...]}; step 0 is the initial state,
each later step holds the action, validity, planner result, clipping, proprioception, the
evaluator-only object poses and the success flags. Evaluator-only: never show it to a model.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from vabench.sim_mjx.batch import BatchBase, SimBatch, proprio_fields
from vabench.sim_mjx.cpu import CpuBatch
from vabench.tasks import REGISTRY, get_task


def _observe(batch: BatchBase, task: Any) -> dict[str, Any]:
    qpos = batch.qpos()[0]
    grip = batch.grip_open()[0]
    flags = task.success(batch.objects, batch.init_qpos()[0], qpos, grip)
    return {
        "proprio": proprio_fields(batch.proprio(), 0, batch.arms),
        "objects": batch.object_poses(0),
        "success": bool(flags["success"]),
        "checks": {k: bool(v) for k, v in flags.items() if k != "success"},
    }


def replay(task_name: str, seed: int, actions: list[Any], backend: str = "mjx") -> dict[str, Any]:
    task = get_task(task_name)
    model = task.build_model()
    batch: BatchBase = SimBatch(model, 1) if backend == "mjx" else CpuBatch(model, 1)
    batch.reset([0], task.initial_qpos(model, seed)[None], settle_steps=task.settle_steps)  # type: ignore[attr-defined]
    steps = [{"index": 0, **_observe(batch, task)}]
    for i, action in enumerate(actions, start=1):
        res = batch.step([action])[0]
        assert res is not None
        step: dict[str, Any] = {
            "index": i,
            "action": action,
            "valid": res.valid,
            "error": res.error,
            "planner_success": res.planner_success,
            "clipped": res.clipped,
            "executed_mm": res.executed_mm,
        }
        steps.append({**step, **_observe(batch, task)})
    return {"task": task_name, "seed": seed, "backend": backend, "steps": steps}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vabench.replay", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--task", required=True, help=f"one of {sorted(REGISTRY)}")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument(
        "--actions", type=Path, required=True, help="JSON file: a list of action objects"
    )
    parser.add_argument(
        "--backend", choices=("mjx", "c"), default="mjx", help="MJX (default) or C MuJoCo"
    )
    parser.add_argument(
        "--json", action="store_true", help="print the JSON document (the only output form now)"
    )
    args = parser.parse_args(argv)
    if args.task not in REGISTRY:
        parser.error(f"--task: unknown task {args.task!r}; valid tasks: {sorted(REGISTRY)}")
    try:
        actions = json.loads(args.actions.read_text())
    except (OSError, json.JSONDecodeError) as err:
        parser.error(f"--actions: cannot read a JSON list from {args.actions}: {err}")
    if not isinstance(actions, list):
        parser.error(f"--actions: {args.actions} must hold a JSON list of action objects")
    doc = replay(args.task, args.seed, actions, args.backend)
    json.dump(doc, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
