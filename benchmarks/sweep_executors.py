"""One sweep, two executors, side by side: `local` (one process) against `processes` (one
worker process per (model, track, task) cell, `--workers` at once).

    python benchmarks/sweep_executors.py [--seeds 4] [--runs 1] [--workers 11] [--size 1280x960]
        [--render-workers 2]

The workload is `configs/all.yaml`'s model, the reference-servo agent (a real CPU-bound
policy: it decodes and segments every image), on the active track over the 11 single-arm base
families, their first `--seeds` verified seeds, `--runs` runs, C MuJoCo. Both sweeps run the
same plan into fresh directories, one after the other; printed: wall time of each, their
ratio, episodes per hour, and whether both ended with the same records (they must: the agent
and the C simulator are deterministic; see `records` for the one accounting field that may
differ).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sweep import run_sweep  # benchmarks/sweep.py: one timed sweep command

from vabench.run_layout import RunDir
from vabench.tasks import BASE_FAMILIES, get_task

SINGLE_ARM = [n for n in BASE_FAMILIES if len(get_task(n).arms) == 1]
TIMING = {"wall_s", "started_at"}


def records(run_dir: Path) -> dict[tuple, dict]:
    """Outcome fields of every record. Input tokens are compared as a total: the embedded
    server simulates a prompt cache shared by the episodes it serves, so the cached share of
    an episode's input depends on which requests came before it (another process, another
    order), while the tokens sent do not."""
    out = {}
    for line in RunDir(run_dir).results.read_text().splitlines():
        r = json.loads(line)
        t = r.pop("tokens")
        r["tokens"] = (t["input"] + t["cached_input"] + t["cache_write"], t["output"])
        out[(r["model"], r["track"], r["task"], r["seed"], r["run"])] = {
            k: v for k, v in r.items() if k not in TIMING
        }
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--runs", type=int, default=1)
    p.add_argument("--workers", type=int, default=len(SINGLE_ARM))
    p.add_argument("--size", default="1280x960")
    p.add_argument("--render-workers", type=int, default=2)
    args = p.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    base = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs/all.yaml").read_text())
    base |= {
        "tracks": ["active"],
        "tasks": SINGLE_ARM,
        "seeds": {"verified": args.seeds},
        "runs": args.runs,
        "render": {"width": width, "height": height, "workers": args.render_workers},
    }
    episodes = len(SINGLE_ARM) * args.seeds * args.runs
    walls = {}
    with tempfile.TemporaryDirectory(prefix="vabench-executors-") as tmp:
        for kind in ("local", "processes"):
            doc = base | {"executor": {"kind": kind, "max_tasks": args.workers}}
            config = Path(tmp) / f"{kind}.yaml"
            config.write_text(yaml.safe_dump(doc, sort_keys=False))
            walls[kind] = run_sweep(config, Path(tmp) / kind, report=False)
            print(f"{kind}: {walls[kind]:.1f} s", flush=True)
        local, processes = records(Path(tmp) / "local"), records(Path(tmp) / "processes")
    differ = [k for k in local if local[k] != processes.get(k)]
    for k in differ[:8]:
        fields = {
            f: (local[k][f], processes[k].get(f))
            for f in local[k]
            if local[k][f] != processes[k].get(f)
        }
        print(f"differs: {'/'.join(map(str, k))}: {fields}")
    print(f"\n{episodes} episodes, {args.size}, {os.cpu_count()} cores, {args.workers} workers")
    print("| executor | wall s | episodes/h | x local |")
    print("|---|---|---|---|")
    for kind, wall in walls.items():
        ratio = walls["local"] / wall
        print(f"| {kind} | {wall:.1f} | {episodes / wall * 3600:,.0f} | {ratio:.2f} |")
    print(f"records equal: {not differ} ({len(differ)} of {len(local)} differ)")


if __name__ == "__main__":
    main()
