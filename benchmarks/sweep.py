"""Sweep wall time against the ideal set by model latency and the concurrency limit.

    python benchmarks/sweep.py [--episodes 1000] [--latency 1] [--steps 5] [--concurrency 200]
        [--backend c|warp|mjx] [--size 320x240] [--render-workers 2] [--skip-smoke] [--json FILE]

1. `configs/smoke.yaml` as a user runs it (a subprocess, report included): wall time.
2. A sweep of `--episodes` episodes (one embedded model, both tracks, 5 tasks, their verified
   seeds, as many runs as needed) whose every reply takes exactly `--latency` seconds, each
   episode `--steps` decisions, at most `--concurrency` episodes in flight. With a free
   simulator and renderer it would take ceil(episodes / concurrency) * steps * latency: the
   ideal. Printed: wall time, ideal, their ratio, episodes per hour (report excluded, timed
   apart).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TASKS = [
    "grasp_single_cube",
    "place_single_cube",
    "grasp_single_pen",
    "click_bell_right",
    "lift_pot",
]


def run_sweep(config: Path, out: Path, report: bool, log: Path | None = None) -> float:
    """Wall time of one sweep command; its output goes to `log` (default: out/../<name>.log)."""
    cmd = [sys.executable, "-m", "vabench.sweep", str(config), "--out", str(out), "--plain"]
    if not report:
        cmd.append("--no-report")
    log = log or out.with_suffix(".log")
    t0 = time.perf_counter()
    with open(log, "w") as f:
        code = subprocess.run(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT).returncode
    wall = time.perf_counter() - t0
    if code not in (0, 1):
        raise SystemExit(f"sweep failed ({code}):\n{log.read_text()[-3000:]}")
    return wall


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--latency", type=float, default=1.0)
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--concurrency", type=int, default=200)
    p.add_argument("--backend", choices=("c", "warp", "mjx"), default="c")
    p.add_argument("--size", default="320x240")
    p.add_argument("--render-workers", type=int, default=2)
    p.add_argument("--skip-smoke", action="store_true")
    p.add_argument("--json")
    p.add_argument("--log", type=Path, help="write the big sweep's output here")
    args = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        if not args.skip_smoke:
            wall = run_sweep(ROOT / "configs/smoke.yaml", tmp_path / "smoke", report=True)
            print(f"configs/smoke.yaml: {wall:.1f} s (8 episodes, report included)")
            rows.append({"sweep": "smoke", "wall_s": wall})

        sys.path.insert(0, str(ROOT))
        from vabench.run_layout import RunDir
        from vabench.tasks.manifests import verified_seeds

        seeds_per_task = len(verified_seeds(TASKS[0]))
        per_run = len(TASKS) * 2 * seeds_per_task
        runs = math.ceil(args.episodes / per_run)
        width, height = (int(v) for v in args.size.split("x"))
        config = {
            "name": "bench",
            "models": [
                {
                    "name": "local",
                    "api": "openai_chat",
                    "base_url": "embedded",
                    "limits": {"max_concurrency": args.concurrency + 8},
                }
            ],
            "embedded_server": {
                "policy": "conversation_hash",
                "latency": {"mean_s": args.latency, "dist": "fixed"},
            },
            "tracks": ["active", "passive"],
            "tasks": TASKS,
            "seeds": "verified",
            "runs": runs,
            "step_budget": args.steps,
            "simulator": {"backend": args.backend},
            "render": {"width": width, "height": height, "workers": args.render_workers},
            "executor": {"max_tasks": len(TASKS), "max_episodes": args.concurrency},
        }
        path = tmp_path / "bench.yaml"
        path.write_text(json.dumps(config))
        n = per_run * runs
        ideal = math.ceil(n / args.concurrency) * args.steps * args.latency
        wall = run_sweep(path, tmp_path / "bench", report=False, log=args.log)
        lines = RunDir(tmp_path / "bench").results.read_text().splitlines()
        results = [json.loads(x) for x in lines]
        scored = sum(r["status"] in ("success", "failure") for r in results)
        t0 = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "vabench.report", str(tmp_path / "bench")],
            cwd=ROOT,
            capture_output=True,
            check=True,
        )
        report_s = time.perf_counter() - t0
        row = {
            "sweep": "latency",
            "episodes": n,
            "scored": scored,
            "concurrency": args.concurrency,
            "latency_s": args.latency,
            "steps": args.steps,
            "backend": args.backend,
            "size": args.size,
            "wall_s": wall,
            "ideal_s": ideal,
            "ratio": ideal / wall,
            "episodes_per_hour": n / wall * 3600,
            "report_s": report_s,
        }
        rows.append(row)
        print(
            f"{n} episodes ({scored} scored), concurrency {args.concurrency}, latency "
            f"{args.latency} s, {args.steps} steps, backend {args.backend}, {args.size}: "
            f"wall {wall:.1f} s, ideal {ideal:.1f} s, x ideal {ideal / wall:.2f}, "
            f"{n / wall * 3600:.0f} episodes/h; report {report_s:.1f} s"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
