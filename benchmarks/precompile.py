"""How long does a fresh machine take to compile Warp's kernels for K families, the old way
against the new (vabench/tuning/precompile.py)?

    python benchmarks/precompile.py [--families grasp_single_cube,lift_pot,place_shoe]
        [--device cpu] [--size 64x48] [--processes N] [--json OUT]

Both schemes start from an empty Warp kernel cache (WARP_CACHE_PATH) and no markers, one after
the other in this run:

- old: one child process per family, all side by side (at most one per core), each compiling
  every module its family launches: the modules the families share are compiled by every child
  at once (Warp has no cross-process lock; the last rename wins);
- new: `precompile.ensure_compiled` (every family's child at once, its modules found and
  loaded ahead in threads, each module compiled by whichever child claims it first; the
  others wait for it and read it from the cache);
- critical: the same with `--first` families on the sweep's critical path (their children
  first, the others at a lower CPU priority: `precompile.child_plan`).

`--schemes` picks which, in that order (default old,new); the ratio is the first's wall over
the second's, and each scheme's line gives every family's seconds (the `--first` family's is
what a fresh machine's suite waits for).

Prints each scheme's wall time, the modules compiled in all and per family (each child reports
them through `precompile.STATS_ENV`), and the ratio. On Warp's CPU device each child also
steps its family's expert's first actions (`precompile.EXPERT_STEPS`) on the CPU, which the
GPU does in seconds: the CPU ratio understates the GPU's; the module counts carry over. (On
Warp's CPU device Warp answers MuJoCo Warp's occupancy queries without loading a module: the
bug that kept the first step from finding modules on a GPU, 2026-11-27, shows only there.)
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from vabench.tuning import precompile


def run_scheme(name: str, families: list[str], args: argparse.Namespace, root: Path) -> dict:
    base = root / name
    stats = base / "stats"
    stats.mkdir(parents=True)
    os.environ.update(
        WARP_CACHE_PATH=str(base / "warp"),
        VABENCH_CACHE=str(base / "vabench"),
        **{precompile.STATS_ENV: str(stats)},
    )
    width, height = (int(v) for v in args.size.split("x"))
    workers = max(1, min(len(families), args.processes or os.cpu_count() or 1))
    started = time.monotonic()
    if name == "old":
        with ThreadPoolExecutor(workers) as pool:
            done = pool.map(
                lambda t: precompile._child(t, (width, height), args.device, 1), families
            )
            failed = [t for t, err in zip(families, done, strict=True) if err]
    else:
        first = set(args.first.split(",")) if name == "critical" and args.first else set()
        failed = precompile.ensure_compiled(
            families, width, height, args.device, processes=args.processes, first=first
        )
    wall = time.monotonic() - started
    per: dict[str, Any] = {}
    for family in families:
        path = stats / f"{family}.json"
        per[family] = json.loads(path.read_text()) if path.exists() else None
    compiled = [n for r in per.values() if r for n in r["compiled"]]
    compile_s = sum(r["compile_s"] for r in per.values() if r)
    return {
        "scheme": name,
        "wall_s": round(wall, 1),
        "failed": failed,
        "modules_compiled": len(compiled),
        "distinct": len(set(compiled)),
        "compile_s": round(compile_s, 1),
        "per_family": {
            t: (len(r["compiled"]), round(r["s"], 1)) if r else None for t, r in per.items()
        },
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--families", default="grasp_single_cube,lift_pot,place_shoe")
    parser.add_argument("--device", default="cpu", help="the Warp device: cpu or cuda:N")
    parser.add_argument("--size", default="64x48", help="WxH of the images")
    parser.add_argument("--processes", type=int, default=None, help="default: the cores")
    parser.add_argument("--json", type=Path, help="write the results here too")
    parser.add_argument("--schemes", default="old,new", help="of old, new, critical")
    parser.add_argument(
        "--first", default="put_everything_in_basket", help="the critical scheme's families"
    )
    args = parser.parse_args()
    schemes = args.schemes.split(",")
    if len(schemes) != 2 or not set(schemes) <= {"old", "new", "critical"}:
        parser.error("--schemes: two of old, new, critical")
    families = args.families.split(",")
    if args.device == "cpu":
        os.environ["VABENCH_WARP_DEVICE"] = "cpu"
    root = Path(tempfile.mkdtemp(prefix="vabench-precompile-"))
    results = []
    try:
        for name in schemes:
            results.append(run_scheme(name, families, args, root))
            print(json.dumps(results[-1]), flush=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    a, b = results
    print(f"\n{len(families)} families on {args.device}, {os.cpu_count()} cores, {args.size}")
    print("| scheme | wall s | modules compiled (distinct) | compiling, s summed", end=" ")
    print("| per family: compiled, s |")
    print("|---|---|---|---|---|")
    for r in results:
        fam = ", ".join(f"{t} {v[0]}, {v[1]}" for t, v in r["per_family"].items() if v)
        cells = [r["scheme"], r["wall_s"], f"{r['modules_compiled']} ({r['distinct']})"]
        print("| " + " | ".join(str(c) for c in [*cells, r["compile_s"], fam]) + " |")
    print(
        f"\n{a['scheme']} / {b['scheme']} wall: {a['wall_s'] / max(b['wall_s'], 1e-9):.2f}x",
        end="; ",
    )
    print(f"compiling: {a['compile_s'] / max(b['compile_s'], 1e-9):.2f}x")
    for family in args.first.split(","):
        times = [r["per_family"].get(family) for r in results]
        if all(times):
            print(
                f"{family}: "
                + ", ".join(f"{r['scheme']} {t[1]} s" for r, t in zip(results, times, strict=True))
            )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 1 if a["failed"] or b["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
