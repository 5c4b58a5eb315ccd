"""The sweep's critical path: the five-object basket's decision physics, today's against each lever.

    python benchmarks/critical_path.py [--sizes 15,30,60] [--actions 12]
        [--variants fixed,at_rest] [--backend warp|c] [--json OUT] [--compile-threads N]

`put_everything_in_basket` bounds the wall time of `configs/all.yaml` on every GPU count: its
episodes are ~181 sequential decisions, each one action of the whole batch. For each batch
size and variant this runs the family's expert closed loop in every slot (the verified seeds,
cycling) for `--actions` batched actions and times each action's physics (`_execute`: the
plan, the substeps, the merge and the observation, until the host has the results), then
prints per variant: seconds an action, substeps the loop ran (the batch's longest slot) and
the slots' mean, seconds a substep, the solver's iterations at the action's last substep
(MuJoCo Warp's `solver_niter`, mean and max over slots), and the ratio of each variant's
action time to the first variant's at the same size, all measured in one run.

Variants (`VARIANTS`): `fixed` (every action 0.8 s of substeps: today's), `at_rest` (an action
ends at its rest substep), `paced` (a move's time follows its length, then ends at rest;
`sim_mjx.controller.ACTION_ENDS`), and `paced_sleep` / `fixed_sleep`, a probe of MuJoCo Warp's
sleeping (`mjENBL_SLEEP` on the scene: trees at rest leave the solve until touched): the
engine does not offer it, since a slot's sleep state is not part of the batch's merge and
reset, so of these rows only the time and the share of trees awake (`awake`) count. Warp's
kernels are compiled in threads before anything is timed (`tuning.warp_ahead`), and a warm-up
action of each batch is left out of the figures; each row is printed and written to `--json`
as soon as it is measured, so a run stopped by a time limit keeps the rows it made. The
basket's decision split (images, model, engine) comes from the main job's timeline, not from
here.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from vabench.sim_mjx.reset_cache import SettledCache
from vabench.tasks import get_task
from vabench.tasks.manifests import verified_seeds
from vabench.tasks.task_batch import TaskBatch, run_experts

TASK = "put_everything_in_basket"
VARIANTS: dict[str, dict[str, Any]] = {
    "fixed": {},
    "at_rest": {"action_end": "at_rest"},
    "paced": {"action_end": "paced"},
    "fixed_sleep": {"sleep": True},
    "paced_sleep": {"action_end": "paced", "sleep": True},
}


@contextlib.contextmanager
def sleeping(on: bool) -> Iterator[None]:
    """MuJoCo Warp's sleeping enabled on every model the batch puts on the device (the probe
    variants): `put_model` and `put_data` read the flag from the MuJoCo model they are given."""
    if not on:
        yield
        return
    import mujoco
    import mujoco_warp as mjw

    originals = mjw.put_model, mjw.put_data
    bit = int(mujoco.mjtEnableBit.mjENBL_SLEEP)

    def flagged(put: Any) -> Any:
        def call(mjm: Any, *args: Any, **kwargs: Any) -> Any:
            before = int(mjm.opt.enableflags)
            mjm.opt.enableflags = before | bit
            try:
                return put(mjm, *args, **kwargs)
            finally:
                mjm.opt.enableflags = before

        return call

    mjw.put_model, mjw.put_data = (flagged(f) for f in originals)
    try:
        yield
    finally:
        mjw.put_model, mjw.put_data = originals


class Timed:
    """Wraps a batch's `_execute`: the wall time, substeps and solver iterations of each call."""

    def __init__(self, batch: Any):
        self.batch = batch
        self.inner = batch._execute
        self.rows: list[dict[str, float]] = []
        batch._execute = self

    def __call__(self, rows: Any) -> Any:
        t0 = time.perf_counter()
        info = self.inner(rows)  # returns once the host has the action's results
        s = time.perf_counter() - t0
        acted = np.asarray(info.executed, bool)
        sub = np.asarray(self.batch.last_substeps)[acted] if acted.any() else np.zeros(1)
        row = {"s": s, "max_substeps": float(sub.max()), "mean_substeps": float(sub.mean())}
        niter = getattr(getattr(self.batch, "_d", None), "solver_niter", None)
        if niter is not None and acted.any():
            it = niter.numpy()[acted]
            row |= {"niter_mean": float(it.mean()), "niter_max": float(it.max())}
        awake = getattr(getattr(self.batch, "_d", None), "tree_awake", None)
        if awake is not None and awake.shape[-1] and acted.any():
            row["awake"] = float(awake.numpy()[acted].mean())
        self.rows.append(row)
        return info


def measure(
    size: int, variant: str, backend: str, actions: int, cache: SettledCache
) -> dict[str, Any]:
    task = get_task(TASK)
    kwargs = dict(VARIANTS[variant])
    sleep = bool(kwargs.pop("sleep", False))
    if backend == "c":
        kwargs["threads"] = min(size, os.cpu_count() or 1)
    t0 = time.perf_counter()
    with sleeping(sleep and backend == "warp"):
        tb = TaskBatch(task, size, backend=backend, cache=cache, **kwargs)
    seeds = verified_seeds(TASK)
    slot_seeds = [seeds[i % len(seeds)] for i in range(size)]
    timed = Timed(tb.batch)
    episodes = run_experts(tb, slot_seeds, max_steps=actions + 1)
    built_s = time.perf_counter() - t0
    rows = timed.rows[1:]  # the first action captured its graph
    tb.batch.close()
    if not rows:
        return {"size": size, "variant": variant, "error": "no action after the warm-up"}
    out: dict[str, Any] = {
        "size": size,
        "variant": variant,
        "backend": backend,
        "actions": len(rows),
        "action_s": float(np.median([r["s"] for r in rows])),
        "max_substeps": float(np.mean([r["max_substeps"] for r in rows])),
        "mean_substeps": float(np.mean([r["mean_substeps"] for r in rows])),
        "episodes_solved": sum(ep.success for ep in episodes),
        "wall_s": built_s,
    }
    out["substep_ms"] = 1e3 * out["action_s"] / max(out["max_substeps"], 1.0)
    if "niter_mean" in rows[0]:
        out["niter_mean"] = float(np.mean([r["niter_mean"] for r in rows]))
        out["niter_max"] = float(np.max([r["niter_max"] for r in rows]))
    if "awake" in rows[0]:
        out["awake"] = float(np.mean([r["awake"] for r in rows]))
    return out


def compile_first(threads: int) -> None:
    from vabench.tuning.warp_ahead import load_ahead

    t0 = time.perf_counter()
    ahead = load_ahead(get_task(TASK), None, threads)
    print(
        f"compiled {ahead.modules} Warp modules ahead in {time.perf_counter() - t0:.1f} s",
        flush=True,
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="15,30,60")
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--backend", default="warp", choices=("warp", "c"))
    p.add_argument("--actions", type=int, default=12, help="timed actions per row")
    p.add_argument("--compile-threads", type=int, default=os.cpu_count() or 1)
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    variants = args.variants.split(",")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        p.error(f"--variants: unknown {unknown}; valid: {sorted(VARIANTS)}")
    if args.backend == "warp":
        compile_first(args.compile_threads)
    cache = SettledCache.default()
    rows: list[dict[str, Any]] = []
    print(
        "size  variant   action s  substeps (max/mean)  ms/substep  niter (mean/max)  vs first",
        flush=True,
    )
    for size in (int(s) for s in args.sizes.split(",")):
        base: float | None = None
        for variant in variants:
            try:
                row = measure(size, variant, args.backend, args.actions, cache)
            except Exception as exc:  # a probe that MuJoCo Warp refuses ends its row, not the run
                row = {"size": size, "variant": variant, "error": f"{type(exc).__name__}: {exc}"}
            rows.append(row)
            if "error" in row:
                print(f"{size:4d}  {variant:8s}  {row['error']}", flush=True)
                continue
            base = base or row["action_s"]
            row["ratio"] = row["action_s"] / base
            niter = (
                f"{row['niter_mean']:6.1f} / {row['niter_max']:4.0f}"
                if "niter_mean" in row
                else "     -"
            )
            print(
                f"{size:4d}  {variant:8s}  {row['action_s']:8.4f}  {row['max_substeps']:6.1f} / "
                f"{row['mean_substeps']:6.1f}       {row['substep_ms']:7.3f}     {niter}"
                f"      {row['ratio']:.2f}"
                + (f"  awake {row['awake']:.2f}" if "awake" in row else ""),
                flush=True,
            )
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
