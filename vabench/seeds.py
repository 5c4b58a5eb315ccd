"""Seed screening: which seeds of each family are verified solvable through the model interface.

    python -m vabench.seeds verify [--task T ...] [--backend c|warp|mjx] [--n 20]
    python -m vabench.seeds table

For each family, candidates 1000, 1001, ... are reset in one batch, settled (2,000 physics steps
plus 500 observed; rejected if any object turns more than 3 deg in the last 200 or any pose is
not finite), and the family's expert is run through the batch with the model's own JSON actions.
The first `n` candidates whose expert succeeds within the step budget are retained. The manifest
`configs/seeds/<task>.json` records the retained seeds, how many candidates were probed (up to
and including the last retained one, as in the paper's yield table) and why each rejected
candidate failed. `table` prints the yield table in the paper's form from the manifests.
Reading a manifest (`verified_seeds`, `load_manifest`) is `vabench.tasks.manifests`.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco

from vabench.sim_mjx.backends import BackendUnavailable, Physics
from vabench.sim_mjx.cli import add_physics_arguments, physics_flag, physics_of
from vabench.tasks import BENCHMARK_FAMILIES, REGISTRY, benchmark_tasks, get_task
from vabench.tasks.base import Task
from vabench.tasks.manifests import MANIFEST_DIR, MANIFEST_VERSION, load_manifest, manifest_path
from vabench.tasks.task_batch import TaskBatch, run_experts

FIRST_CANDIDATE = 1000
N_RETAINED = 20


@dataclass
class Manifest:
    task: str
    retained: list[int]
    probed: int
    rejected: dict[int, str]
    backend: str
    expert_steps: dict[int, int] = field(default_factory=dict)
    seconds: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {
            "version": MANIFEST_VERSION,
            "task": self.task,
            "retained": self.retained,
            "probed": self.probed,
            "rejected": {str(k): v for k, v in sorted(self.rejected.items())},
            "expert_steps": {str(k): v for k, v in sorted(self.expert_steps.items())},
            "screening": {
                "first_candidate": FIRST_CANDIDATE,
                "backend": self.backend,
                "mujoco": mujoco.__version__,
                "settle_steps": 2000,
                "observe_steps": 500,
                "max_drift_deg": 3.0,
                "date": dt.date.today().isoformat(),
            },
        }


def screen(
    task: Task,
    n: int = N_RETAINED,
    backend: str | Physics = "c",
    batch_size: int | None = None,
    max_candidates: int = 200,
    log: Any = None,
    **batch_kwargs: Any,
) -> Manifest:
    """Screen candidates in order, a whole batch of them per round, until `n` are retained."""
    t0 = time.perf_counter()
    size = batch_size or n
    tb = TaskBatch(task, size, backend=backend, **batch_kwargs)
    retained: list[int] = []
    rejected: dict[int, str] = {}
    steps: dict[int, int] = {}
    probed = 0
    next_seed = FIRST_CANDIDATE
    while len(retained) < n and next_seed < FIRST_CANDIDATE + max_candidates:
        seeds = list(range(next_seed, min(next_seed + size, FIRST_CANDIDATE + max_candidates)))
        next_seed = seeds[-1] + 1
        for ep in run_experts(tb, seeds):  # in seed order
            if len(retained) == n:
                break  # candidates after the n-th success are not part of the yield
            probed += 1
            if ep.success:
                retained.append(ep.seed)
                steps[ep.seed] = ep.steps
            else:
                rejected[ep.seed] = ep.end
        if log:
            log(f"{task.name}: {len(retained)}/{n} retained after {probed} probed")
    return Manifest(
        task.name, retained, probed, rejected, tb.physics.label, steps, time.perf_counter() - t0
    )


def yield_table(manifests: list[dict[str, Any]]) -> str:
    """The paper's tab:seed-probe-yield: probed, retained, yield per family and overall."""
    rows = [("Task", "Probed", "Retained", "Yield (%)")]
    total_p = total_r = 0
    for m in manifests:
        p, r = m["probed"], len(m["retained"])
        total_p, total_r = total_p + p, total_r + r
        rows.append((m["task"], str(p), str(r), f"{100.0 * r / max(p, 1):.1f}"))
    rows.append(
        (
            f"All {len(manifests)} tasks",
            str(total_p),
            str(total_r),
            f"{100.0 * total_r / max(total_p, 1):.1f}",
        )
    )
    width = max(len(r[0]) for r in rows)
    lines = [f"{r[0]:<{width}}  {r[1]:>6}  {r[2]:>8}  {r[3]:>9}" for r in rows]
    lines.insert(1, "-" * len(lines[0]))
    lines.insert(len(lines) - 1, "-" * len(lines[0]))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vabench.seeds", description=__doc__.split("\n")[0]
    )
    sub = parser.add_subparsers(dest="command", required=True)
    verify = sub.add_parser("verify", help="screen candidates and write the manifests")
    verify.add_argument("--task", action="append", help="a family (repeatable); default: all")
    add_physics_arguments(verify, backend="c")
    verify.add_argument("--n", type=int, default=N_RETAINED, help="seeds to retain")
    verify.add_argument("--batch", type=int, default=None, help="candidates per batch (default n)")
    verify.add_argument("--max-candidates", type=int, default=200)
    verify.add_argument("--out", type=Path, default=MANIFEST_DIR)
    table = sub.add_parser("table", help="print the yield table from the manifests")
    table.add_argument("--dir", type=Path, default=MANIFEST_DIR)
    args = parser.parse_args(argv)

    if args.command == "table":
        docs = [
            load_manifest(t, args.dir)
            for t in BENCHMARK_FAMILIES
            if manifest_path(t, args.dir).exists()
        ]
        print(yield_table(docs))
        return 0
    physics = physics_of(parser, args)
    names = args.task or [t.name for t in benchmark_tasks()]
    for name in names:
        if name not in REGISTRY:
            parser.error(f"--task: unknown task {name!r}; valid tasks: {sorted(REGISTRY)}")
    if args.n < 1:
        parser.error("--n must be >= 1")
    args.out.mkdir(parents=True, exist_ok=True)
    docs = []
    for name in names:
        try:
            m = screen(
                get_task(name),
                args.n,
                physics,
                args.batch,
                args.max_candidates,
                log=lambda s: print(s, file=sys.stderr, flush=True),
            )
        except BackendUnavailable as err:
            parser.error(f"{physics_flag(args)}: {err}")
        doc = m.to_json()
        manifest_path(name, args.out).write_text(json.dumps(doc, indent=1) + "\n")
        print(
            f"{name}: {len(m.retained)}/{args.n} retained of {m.probed} probed "
            f"in {m.seconds:.1f} s -> {manifest_path(name, args.out)}",
            file=sys.stderr,
        )
        docs.append(doc)
    print(yield_table(docs))
    return 0 if all(len(d["retained"]) == args.n for d in docs) else 1


if __name__ == "__main__":
    raise SystemExit(main())
