"""Evaluator CLI: execute model-facing actions (or the family's expert) on one task seed and
print every step.

    python -m vabench.replay --task grasp_single_cube --seed 1000 --actions actions.json --json
    python -m vabench.replay --task place_single_cube --seed 1000 --expert --backend c --json

The actions file holds a JSON list of action objects exactly as the model emits them (FACTS.md).
The output is one JSON document {"task", "seed", "backend", "impl", "steps": [...], "success"}
(`--backend warp` is backend "mjx", impl "warp", as records name it); step 0 is
the initial state after the reset's settling; each later step holds the action, validity,
planner result, clipping, proprioception, the evaluator-only object poses, the predicate's
checks, success and the checkpoint reached. Evaluator-only: never show it to a model.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from vabench.sim_mjx.backends import BackendUnavailable, Physics
from vabench.sim_mjx.cli import add_physics_arguments, physics_flag, physics_of
from vabench.sim_mjx.layout import proprio_fields
from vabench.tasks import REGISTRY, get_task
from vabench.tasks.expert import ExpertContext, ExpertFailed
from vabench.tasks.task_batch import StepOutcome, TaskBatch


def _observe(tb: TaskBatch) -> dict[str, Any]:
    ev, _ = tb.evaluate()
    return {
        "proprio": proprio_fields(tb.batch.proprio(), 0, tb.batch.arms),
        "objects": tb.batch.object_poses(0),
        "checks": {k: bool(v[0]) for k, v in ev.checks.items()},
    }


class _ExpertSource:
    """The family's expert as an action source for slot 0 (evaluator-only state)."""

    def __init__(self, tb: TaskBatch):
        sample = tb.samples[0]
        assert sample is not None
        self.tb = tb
        self.ctx = ExpertContext(tb.task.arms, tb.views([0])[0])
        self.script = iter(tb.task.expert(sample, self.ctx))
        self.end: str | None = None

    def next_action(self) -> dict[str, Any] | None:
        try:
            return next(self.script)
        except StopIteration:
            self.end = "expert finished"
        except ExpertFailed as err:
            self.end = f"expert gave up: {err}"
        return None

    def observe(self, out: StepOutcome) -> None:
        view = self.tb.views([0])[0]
        view.last = out.result
        self.ctx.view = view


def replay(
    task_name: str,
    seed: int,
    actions: list[Any] | None,
    backend: str | Physics = "mjx",
    impl: str | None = None,
) -> dict[str, Any]:
    """Run `actions` (None: the expert) on one seed until success, the budget, or the end."""
    task = get_task(task_name)
    tb = TaskBatch(task, 1, backend=backend, impl=impl)
    settle = tb.reset([0], [seed])[0]
    steps: list[dict[str, Any]] = [{"index": 0, **_observe(tb)}]
    expert = _ExpertSource(tb) if actions is None else None
    queue = iter(actions or [])
    success = False
    for i in range(1, task.step_budget + 1):
        action = expert.next_action() if expert else next(queue, None)
        if action is None:
            break
        out: StepOutcome | None = tb.step([action])[0]
        assert out is not None
        if expert:
            expert.observe(out)
        res = out.result
        steps.append(
            {
                "index": i,
                "action": action,
                "valid": res.valid,
                "error": res.error,
                "planner_success": res.planner_success,
                "clipped": res.clipped,
                "executed_mm": res.executed_mm,
                **_observe(tb),
                "success": out.success,
                "checkpoint": tb.checkpoint(0),
            }
        )
        success = out.success
        if success:
            break
    return {
        "task": task_name,
        "seed": seed,
        "backend": tb.backend,
        "impl": tb.impl,
        "source": "expert" if actions is None else "actions",
        "settle": {"finite": settle.finite, "max_drift_deg": round(settle.max_drift_deg, 4)},
        "success": success,
        "expert_end": expert.end if expert else None,
        "steps": steps,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vabench.replay", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--task", required=True, help=f"one of {sorted(REGISTRY)}")
    parser.add_argument("--seed", type=int, required=True)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--actions", type=Path, help="JSON file: a list of action objects")
    source.add_argument("--expert", action="store_true", help="run the family's expert")
    add_physics_arguments(parser)
    parser.add_argument(
        "--json", action="store_true", help="print the JSON document (the only output form now)"
    )
    args = parser.parse_args(argv)
    if args.task not in REGISTRY:
        parser.error(f"--task: unknown task {args.task!r}; valid tasks: {sorted(REGISTRY)}")
    actions = None
    if args.actions is not None:
        try:
            actions = json.loads(args.actions.read_text())
        except (OSError, json.JSONDecodeError) as err:
            parser.error(f"--actions: cannot read a JSON list from {args.actions}: {err}")
        if not isinstance(actions, list):
            parser.error(f"--actions: {args.actions} must hold a JSON list of action objects")
    try:
        doc = replay(args.task, args.seed, actions, physics_of(parser, args))
    except BackendUnavailable as err:
        parser.error(f"{physics_flag(args)}: {err}")
    json.dump(doc, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
