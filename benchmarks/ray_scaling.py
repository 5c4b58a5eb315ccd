"""Scaling of a Ray sweep with its engines: the same work on 1, 2, 4, 8 engine actors of one
host, episodes per second and the ratio to perfect scaling, side by side.

    python benchmarks/ray_scaling.py [--engines 1,2,4,8] [--backend auto|c|warp|mjx] [--seeds 20]
        [--runs 3] [--tracks active,passive,transfer,long_horizon] [--tasks base]
        [--steps N] [--size 1280x960] [--policy reference_servo] [--latency S] [--warmup]
        [--per-gpu K] [--dealing machine|budgets,measured] [--json FILE] [--keep DIR]

The defaults are `configs/all.yaml` as shipped (2,160 episodes of the reference-servo agent
on every track); the options shrink it (the test of this script runs it at a tiny size on CPU
engines). Each engine count runs the whole plan into a fresh run directory, one after the
other, on one local Ray instance started here:

- on a host with GPUs (backend auto, warp or mjx), each count is of GPUs, each GPU shared by
  `--per-gpu` engines (default: the sweep's own, 4 under CUDA MPS where NVIDIA's control program
  is installed, else 1); counts above the GPUs present are skipped;
- without (backend c), engines of `1 + render.workers` CPUs each; Ray is told the host has as
  many CPUs as the largest count needs (more than it has, on a small machine: the engines then
  share its cores, which the printed core count shows).

`--per-gpu K` (GPUs only): each GPU shared by K engine processes (`executor.actors` = K x
GPUs) under one CUDA MPS daemon of the sweep's on the host (`tuning.mps.join_node_daemon`), as
the local sweep runs 4 a GPU; with K > 1 Ray is restarted for each count with only that many
GPUs. `--per-gpu 1` is one engine a GPU (the A/B: on 2 x H200, 2026-11-29, four a GPU were
1.42-1.45x one).

`--dealing budgets,measured` runs each count twice, side by side: first with this machine's
paces hidden, so the driver deals chunks by step budgets (a new machine's first sweep), then
with the paces that run measured, so it deals by each task's measured seconds an episode
(`sweep.cells.episode_costs`); the pace file is put back as it was at the end. The default,
`machine`, deals by whatever this machine's pace file holds, once.

`--warmup` first runs every planned (task, seed) for one step on the most engines, untimed:
on a fresh GPU machine that compiles Warp's kernels and fills the settled-state cache
(`VABENCH_STATE_CACHE`), which the first count would otherwise pay alone.

Printed per count: wall time of the sweep (engine start-up included), the steady rate
(episodes / the span from the first episode's start to the last one's end, from the records),
and the scaling ratio rate(N) / (N x rate(1)) on both. Then per engine (the driver's
`engine_report`): its seconds of start-up, working (a chunk or more) and waiting for work, its
episodes, and its GPU's busy share over its life (sampled by the engine through nvidia-smi; GPUs
only). And where the lost time goes: with the same episodes, 1 - ratio = (N x wall - wall(1)) /
(N x wall), and the engine-seconds N x wall split into start-up, working, waiting and the
driver's own (before the engines, after them), so the shortfall is the sum of each part's
excess over the first count's: more start-up, more waiting for work (placement, the tail: an
engine idle while another holds the basket), or more working seconds for the same episodes
(engines slowing each other: shared cores, a shared GPU, the driver).

Whether every count recorded every planned episode once is checked, and the outcomes (success
per episode) are compared with the first count's: with the deterministic agent and C MuJoCo
they must agree; on GPUs Warp's contact ordering may differ unless `simulator.deterministic` is
set, so they are only shown.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def device() -> str:
    """What this host is, in words (GPUs by name, CPU model and cores)."""
    try:
        names = subprocess.run(
            ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=20,
        ).stdout.split("\n")
        gpus = [n.strip() for n in names if n.strip()]
    except (OSError, subprocess.SubprocessError):
        gpus = []
    cpu = platform.processor() or "CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0))
    gpu_text = f"{len(gpus)} x {gpus[0]}" if gpus else "no GPU"
    return f"{gpu_text}; {cpu}, {cores} cores"


@contextlib.contextmanager
def paces_as(entries: dict | None) -> Iterator[None]:
    """This machine's entries of the pace file (`check.pace.pace_file`) replaced by `entries`
    (None: none at all) for the block, the file's bytes put back after it: the driver deals by
    what the file holds when a sweep starts (`sweep.cells.dealing_costs`)."""
    import socket

    from vabench.check.pace import pace_file

    path = pace_file()
    before = path.read_bytes() if path.exists() else None
    doc = json.loads(before) if before else {}
    doc[socket.gethostname()] = entries or {}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1), encoding="utf-8")
    try:
        yield
    finally:
        if before is None:
            path.unlink(missing_ok=True)
        else:
            path.write_bytes(before)


def measured_entries(run_dir: Path, config_path: Path) -> dict:
    """The pace entries a sweep's end would keep for `run_dir` (`check.pace.keep_pace`)."""
    from dataclasses import asdict

    from vabench.check.pace import measure_kinds
    from vabench.config import load_config

    config = load_config(config_path, overrides={"out": str(run_dir)})
    return {k.kind: asdict(k) for k in measure_kinds(run_dir, config)}


def make_config(args: argparse.Namespace, engines: int, out: Path) -> Path:
    """`configs/all.yaml` shrunk by the options, on `engines` engine actors."""
    doc = yaml.safe_load((ROOT / "configs/all.yaml").read_text())
    width, height = (int(v) for v in args.size.split("x"))
    doc["tracks"] = args.tracks.split(",")
    doc["tasks"] = args.tasks if args.tasks == "base" else args.tasks.split(",")
    doc["seeds"] = {"verified": args.seeds}
    doc["runs"] = args.runs
    if args.steps:
        doc["step_budget"] = args.steps
    doc["simulator"] = {"backend": args.backend}
    doc["render"] |= {"width": width, "height": height, "workers": args.render_workers}
    doc["embedded_server"]["policy"] = args.policy
    if args.latency:
        doc["embedded_server"]["latency"] = {"mean_s": args.latency}
    doc["executor"] = {"kind": "ray", "actors": engines}
    path = out.with_suffix(".yaml")
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def one_count(args: argparse.Namespace, engines: int, tmp: Path, dealing: str = "") -> dict:
    """Run the plan on `engines` engines (GPUs, with `--per-gpu`: that many engines each);
    returns its figures and outcomes (`dealing`: a suffix of the run directory's name)."""
    from vabench.check.pace import machine_paces
    from vabench.config import load_config
    from vabench.config.choices import choose
    from vabench.run_layout import RunDir
    from vabench.sweep.cells import dealing_line
    from vabench.sweep.plan import plan
    from vabench.sweep.ray_executor import run_ray
    from vabench.sweep.rundir import check_run_dir

    out = tmp / f"engines_{engines}{'_' + dealing if dealing else ''}"
    processes = engines * args.per_gpu
    config = load_config(make_config(args, processes, out), overrides={"out": str(out)})
    keys = plan(config)
    check_run_dir(out, config, keys, config.document())
    weighed = dealing_line(config, {k.task for k in keys}, machine_paces())  # as the driver's
    report: list[dict] = []
    t0 = time.perf_counter()
    records = run_ray(config, keys, out, choose(config), on_engines=report.extend)
    wall = time.perf_counter() - t0
    lines = RunDir(out).results.read_text().splitlines()
    recs = [json.loads(x) for x in lines]
    first = min(r["started_at"] for r in recs)
    last = max(r["started_at"] + r["wall_s"] for r in recs)
    return {
        "engines": engines,
        "dealing": dealing or "machine",
        "weighed": weighed,
        "run_dir": str(out),
        "config": str(out.with_suffix(".yaml")),
        "episodes": len(keys),
        "recorded_once": len(recs) == len(records) == len(keys),
        "wall_s": wall,
        "span_s": last - first,
        "episodes_per_s": len(recs) / wall,
        "steady_episodes_per_s": len(recs) / (last - first),
        "success": sum(r["success"] for r in recs),
        "engine_report": report,
        "engine_time": engine_time(report, processes, wall),
        "outcomes": {
            f"{r['model']}/{r['track']}/{r['task']}/{r['seed']}/{r['run']}": r["success"]
            for r in recs
        },
    }


def drop_frames(root: Path) -> None:
    """Remove the episodes' frames under `root` (the kept run directories of `--keep`): their
    events, results and logs are what the timelines read, and a count of `configs/all.yaml`
    writes ~2,160 episodes' JPEGs (1 or 5 a decision), which a GPU host's disk need not hold
    for every count."""
    for frames in [
        *root.glob("*/episodes/*/*/*/*/*/frames"),
        *root.glob("warmup/*/episodes/*/*/*/*/*/frames"),
    ]:
        shutil.rmtree(frames, ignore_errors=True)


PARTS = ("start_up_s", "working_s", "waiting_s", "other_s")


def engine_time(report: list[dict], engines: int, wall: float) -> dict[str, float]:
    """The engine-seconds of a count (engines x wall) split into start-up, working, waiting
    for work and the rest ('other': the driver before and after its engines; an engine started
    in place of a dead one adds its own seconds to the parts)."""
    total = engines * wall
    parts = {k: sum(r[k] for r in report) for k in PARTS[:3]}
    parts["other_s"] = max(total - sum(parts.values()), 0.0)
    return {"total_s": total, **parts}


def lost_time(result: dict, base: dict) -> dict[str, float]:
    """Each part's excess engine-seconds over the first count's, as a share of this count's
    engine-seconds: they sum to 1 - ratio (same episodes in both)."""
    mine, first = result["engine_time"], base["engine_time"]
    return {k: (mine[k] - first[k]) / mine["total_s"] for k in PARTS}


def print_engines(result: dict) -> None:
    for r in result["engine_report"]:
        gpu = f"{r['gpu_busy']:.0%}" if r.get("gpu_busy") is not None else "-"
        where = r.get("host") or "?"
        if r.get("gpus"):
            where += f" GPU {','.join(r['gpus'])}"
        if r.get("lead") is False:  # below its GPU's lead in MPS priority
            where += ", below normal"
        critical = r.get("critical_chunks") or []
        print(
            f"    engine {r['engine']} ({where}): start-up {r['start_up_s']:.1f} s, "
            f"working {r['working_s']:.1f} s, waiting {r['waiting_s']:.1f} s, "
            f"{r['episodes']} episodes in {r.get('chunks', '?')} chunks"
            f"{' (critical: ' + ', '.join(critical) + ')' if critical else ''}, "
            f"GPU busy {gpu}{', died' if r['died'] else ''}",
            flush=True,
        )


def summarise(results: list[dict], first: dict) -> None:
    """The counts of one dealing: rates, the ratio to perfect scaling against its first count,
    whether each recorded every episode once with the outcomes of the benchmark's first run,
    and where the lost time went."""
    base = results[0]
    print(f"\ndealt by {base['dealing']}:")
    print(
        f"{'engines':>7} {'episodes/s':>11} {'ratio':>6} {'steady/s':>9} {'ratio':>6} "
        f"{'once':>5} {'outcomes':>9}"
    )
    for r in results:
        n = r["engines"] / base["engines"]
        r["ratio"] = r["episodes_per_s"] / (n * base["episodes_per_s"])
        r["steady_ratio"] = r["steady_episodes_per_s"] / (n * base["steady_episodes_per_s"])
        r["same_outcomes"] = r["outcomes"] == first["outcomes"]
        print(
            f"{r['engines']:>7} {r['episodes_per_s']:>11.3f} {r['ratio']:>6.2f} "
            f"{r['steady_episodes_per_s']:>9.3f} {r['steady_ratio']:>6.2f} "
            f"{'yes' if r['recorded_once'] else 'NO':>5} "
            f"{'same' if r['same_outcomes'] else 'differ':>9}"
        )
    print("where the lost time goes (engine-seconds beyond the first count's, share of N x wall):")
    print(
        f"{'engines':>7} {'1-ratio':>8} {'start-up':>9} {'working':>8} {'waiting':>8} {'other':>7}"
    )
    for r in results:
        r["lost"] = lost_time(r, base)
        lost = r["lost"]
        print(
            f"{r['engines']:>7} {1 - r['ratio']:>8.3f} {lost['start_up_s']:>9.3f} "
            f"{lost['working_s']:>8.3f} {lost['waiting_s']:>8.3f} {lost['other_s']:>7.3f}"
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--engines", default="1,2,4,8")
    p.add_argument("--backend", choices=("auto", "c", "warp", "mjx"), default="auto")
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--tracks", default="active,passive,transfer,long_horizon")
    p.add_argument("--tasks", default="base", help="base, or a comma-separated list")
    p.add_argument("--steps", type=int, default=0, help="step budget cap (0: the tasks' own)")
    p.add_argument("--size", default="1280x960")
    p.add_argument("--render-workers", type=int, default=2)
    p.add_argument("--policy", default="reference_servo")
    p.add_argument("--latency", type=float, default=0.0, help="the model's reply time, seconds")
    p.add_argument("--warmup", action="store_true", help="one untimed step of every seed first")
    p.add_argument(
        "--per-gpu",
        type=int,
        default=None,
        help="engine processes a GPU (MPS); default: the sweep's own (4 where NVIDIA's MPS "
        "control program is installed, else 1: `tuning.engine_env.engines_per_gpu`)",
    )
    p.add_argument(
        "--dealing",
        default="machine",
        choices=("machine", "budgets", "budgets,measured"),
        help="what the driver deals chunks by: this machine's pace file as it is (machine), "
        "step budgets (budgets), or each count by budgets and then by the seconds that run "
        "measured (budgets,measured), side by side",
    )
    p.add_argument("--json", type=Path)
    p.add_argument(
        "--keep",
        type=Path,
        help="write each count's run directory here and keep it, without the episodes' frames "
        "(default: a temporary folder, removed at the end): benchmarks/episode_timeline.py then "
        "says where each count's decisions spent their time",
    )
    args = p.parse_args()

    if args.keep is not None:  # before Ray starts
        args.keep.mkdir(parents=True, exist_ok=True)
        taken = sorted(f.name for f in args.keep.iterdir())
        if taken:
            p.error(f"--keep {args.keep}: not empty ({', '.join(taken[:3])}): name a new folder")

    import ray

    from vabench.sim_mjx.backends import resolve
    from vabench.tuning.engine_env import engines_per_gpu

    counts = [int(n) for n in args.engines.split(",")]
    on_gpus = resolve(args.backend).batched
    if args.per_gpu is None:  # what a sweep's engines default to
        args.per_gpu = engines_per_gpu() if on_gpus else 1
    if args.per_gpu > 1 and not on_gpus:
        p.error("--per-gpu shares GPUs between engines: it needs a GPU backend (auto, warp, mjx)")
    if on_gpus:
        ray.init(address="local", include_dashboard=False)
        gpus = int(ray.cluster_resources().get("GPU", 0))
        skipped = [n for n in counts if n > gpus]
        counts = [n for n in counts if n <= gpus]
        if skipped:
            print(f"skipped (only {gpus} GPUs here): {skipped}", flush=True)
    else:
        cpus = max(counts) * (1 + args.render_workers)
        cpus = max(cpus, len(os.sched_getaffinity(0)))
        ray.init(address="local", num_cpus=cpus, include_dashboard=False)
    host = device()
    print(f"device: {host}; Ray {ray.__version__}; {datetime.date.today()}", flush=True)
    results = []

    def gpus_for(n: int) -> None:
        """With engines sharing GPUs, a Ray of n GPUs: engines claim their share of those."""
        if on_gpus and args.per_gpu > 1:
            ray.shutdown()
            ray.init(address="local", num_gpus=n, include_dashboard=False)

    where = (
        contextlib.nullcontext(str(args.keep))
        if args.keep is not None
        else tempfile.TemporaryDirectory(prefix="vabench-ray-scaling-")
    )
    with where as tmp:
        if args.warmup and counts:
            warm = argparse.Namespace(**{**vars(args), "tracks": "active", "runs": 1, "steps": 1})
            t0 = time.perf_counter()
            (Path(tmp) / "warmup").mkdir()
            gpus_for(max(counts))
            one_count(warm, max(counts), Path(tmp) / "warmup")
            print(f"warm-up (untimed): {time.perf_counter() - t0:.1f} s", flush=True)
        for n in counts:
            gpus_for(n)
            measured: dict | None = None
            for dealing in args.dealing.split(","):
                paces = {"machine": None, "budgets": {}, "measured": measured}[dealing]
                with contextlib.nullcontext() if paces is None else paces_as(paces):
                    result = one_count(args, n, Path(tmp), "" if dealing == "machine" else dealing)
                if dealing == "budgets":
                    measured = measured_entries(Path(result["run_dir"]), Path(result["config"]))
                if args.keep is not None:
                    drop_frames(Path(tmp))
                results.append(result)
                what = f"{n} GPUs x {args.per_gpu} engines" if args.per_gpu > 1 else f"{n} engines"
                print(
                    f"{what}, dealt by {result['dealing']}: {result['episodes']} episodes in "
                    f"{result['wall_s']:.1f} s ({result['episodes_per_s']:.3f}/s; steady "
                    f"{result['steady_episodes_per_s']:.3f}/s over {result['span_s']:.1f} s)",
                    flush=True,
                )
                print(f"    {result['weighed']}", flush=True)
                print_engines(result)
    ray.shutdown()
    dealings = args.dealing.split(",")
    for dealing in dealings:
        summarise([r for r in results if r["dealing"] == dealing], results[0])
    if dealings == ["budgets", "measured"]:
        print("\ndealt by measured seconds against by budgets, the same count (wall time):")
        for b, m in zip(results[::2], results[1::2], strict=True):
            m["vs_budgets"] = m["wall_s"] / b["wall_s"]
            print(
                f"{m['engines']:>7} {b['wall_s']:>8.1f} s {m['wall_s']:>8.1f} s "
                f"{m['vs_budgets']:>6.2f}x"
            )
    if args.json:
        summary = {
            "device": host,
            "date": str(datetime.date.today()),
            "ray": ray.__version__,
            "args": {k: str(v) for k, v in vars(args).items()},
            "results": [{k: v for k, v in r.items() if k != "outcomes"} for r in results],
        }
        args.json.write_text(json.dumps(summary, indent=2))
        print(f"\nwritten: {args.json}")
    if not all(r["recorded_once"] for r in results):
        sys.exit(1)


if __name__ == "__main__":
    main()
