"""Task CLI: what the families are, and the evaluator-only initial state of a seed.

    python -m vabench.tasks list [--json] [--all]
    python -m vabench.tasks show TASK --seed S [--json]

`list` prints the base families (with --all also development tasks): arms, step budget,
checkpoints, model ids, verified seeds. `show` prints one seed: instruction, arms, budget,
checkpoints, model id and the initial object poses (position + wxyz quaternion) as sampled,
before settling. Evaluator-only output: never show it to a model.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from vabench.tasks import REGISTRY, benchmark_tasks, get_task
from vabench.tasks.base import Task
from vabench.tasks.manifests import manifest_path, verified_seeds


def describe(task: Task) -> dict[str, Any]:
    return {
        "name": task.name,
        "suite": task.suite,
        "instruction": task.instruction,
        "arms": list(task.arms),
        "step_budget": task.step_budget,
        "checkpoints": list(task.checkpoints),
        "model_ids": list(task.variants),
        "verified_seeds": verified_seeds(task.name) if manifest_path(task.name).exists() else [],
    }


def show(task: Task, seed: int) -> dict[str, Any]:
    sample = task.sample(seed)
    return {
        **{k: v for k, v in describe(task).items() if k != "verified_seeds"},
        "seed": seed,
        "model_id": task.variants[sample.variant],
        "params": sample.params,
        "objects": {
            name: {"pos": [float(x) for x in pos], "quat": [float(x) for x in quat]}
            for name, (pos, quat) in sample.poses.items()
        },
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vabench.tasks", description=__doc__.split("\n")[0]
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p_list = sub.add_parser("list", help="the task families")
    p_list.add_argument("--json", action="store_true")
    p_list.add_argument("--all", action="store_true", help="include development tasks")
    p_show = sub.add_parser("show", help="one seed's instruction and initial object poses")
    p_show.add_argument("task")
    p_show.add_argument("--seed", type=int, required=True)
    p_show.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)

    if args.command == "list":
        tasks = list(REGISTRY.values()) if args.all else benchmark_tasks()
        docs = [describe(t) for t in tasks]
        if args.json:
            json.dump(docs, sys.stdout, indent=1)
            sys.stdout.write("\n")
        else:
            for d in docs:
                print(
                    f"{d['name']:<30} arms={','.join(d['arms']):<11} budget={d['step_budget']:<4}"
                    f" model_ids={len(d['model_ids']):<3} verified={len(d['verified_seeds'])}"
                )
        return 0
    if args.task not in REGISTRY:
        parser.error(f"unknown task {args.task!r}; valid tasks: {sorted(REGISTRY)}")
    doc = show(get_task(args.task), args.seed)
    if args.json:
        json.dump(doc, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        for k, v in doc.items():
            print(f"{k}: {v}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
