"""Do several task batches step faster together on one GPU than one after the other?

    python benchmarks/warp_streams.py [--tasks 14] [--worlds 30,150] [--substeps 200] [--json OUT]

Why: on an H100 one action of a Warp batch takes ~90 ms whatever its size up to 256 slots
(docs/PERFORMANCE.md): MuJoCo Warp's kernels over a few dozen worlds occupy a few of the GPU's
132 SMs, and an action is 200 substeps of ~100 small kernels each. A sweep runs one batch per
task family and track (dozens); today every batch of a process queues its work on the device's
one stream under the device lock, so they run one after the other, and the processes executor's
16 CUDA contexts time-slice the GPU (one context at a time). This measures what one process
would gain by giving each batch its own CUDA stream: the same captured substep graphs, launched

- serial: every batch's action on one stream, batch after batch (today's layout);
- streams: each batch on its own stream, the launches interleaved substep by substep, one
  synchronisation at the end (what a stream per WarpBatch would do);

and prints agent actions per second (worlds x batches per round / seconds per round), the
ratio, and the host time spent queueing the launches (the lock would be held that long).
Each batch is the scene of one base family (variant 0) at its home pose; objects settle onto
the table during the warm-up, so contacts are present as in an episode. GPU only: on the CPU
Warp has no streams and the script says so.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

from vabench.sim_mjx.scene import home_qpos
from vabench.tasks import base_tasks


def build(task, worlds: int, settle: int = 200):
    """(model, data, step graph, stream) of one family's scene on the GPU."""
    import mujoco_warp as mjw
    import warp as wp

    from vabench.sim_mjx.warp.model import capacity

    m0 = task.build_models()[0]
    cap = capacity(m0)
    d0 = mujoco.MjData(m0)
    d0.qpos[:] = home_qpos(m0)
    m = mjw.put_model(m0)
    d = mjw.put_data(m0, d0, nworld=worlds, nconmax=cap.nconmax, njmax=cap.njmax)
    device = wp.get_device()
    stream = wp.Stream(device) if device.is_cuda else None
    with wp.ScopedStream(stream) if stream else contextlib.nullcontext():
        mjw.step(m, d)  # loads the modules before capture
        with wp.ScopedCapture(stream=stream) as capture:
            mjw.step(m, d)
        for _ in range(settle):  # contacts as in an episode
            wp.capture_launch(capture.graph, stream=stream)
    wp.synchronize_device()
    return m, d, capture.graph, stream


def round_serial(batches, substeps: int) -> tuple[float, float]:
    import warp as wp

    one = batches[0][3]
    t0 = time.perf_counter()
    for _, _, graph, _ in batches:
        for _ in range(substeps):
            wp.capture_launch(graph, stream=one)
    queued = time.perf_counter() - t0
    wp.synchronize_device()
    return time.perf_counter() - t0, queued


def round_streams(batches, substeps: int) -> tuple[float, float]:
    import warp as wp

    t0 = time.perf_counter()
    for _ in range(substeps):
        for _, _, graph, stream in batches:
            wp.capture_launch(graph, stream=stream)
    queued = time.perf_counter() - t0
    wp.synchronize_device()
    return time.perf_counter() - t0, queued


def measure(batches, worlds: int, substeps: int, repeats: int) -> dict:
    out = {"batches": len(batches), "worlds": worlds}
    modes = [("serial", round_serial)]
    if batches[0][3] is not None:  # streams exist on CUDA devices only
        modes.append(("streams", round_streams))
    for name, fn in modes:
        fn(batches, substeps)  # warm
        times = [fn(batches, substeps) for _ in range(repeats)]
        wall = float(np.median([t for t, _ in times]))
        out[name] = {
            "round_s": wall,
            "queue_s": float(np.median([q for _, q in times])),
            "actions_per_s": len(batches) * worlds / wall,
        }
    if "streams" in out:
        out["ratio"] = out["streams"]["actions_per_s"] / out["serial"]["actions_per_s"]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", type=int, default=14, help="base families, one batch each")
    ap.add_argument("--counts", default="1,4,14", help="batches stepped together")
    ap.add_argument("--worlds", default="30,150", help="slots per batch")
    ap.add_argument("--substeps", type=int, default=200, help="physics steps of one action")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--settle", type=int, default=200, help="steps before timing")
    ap.add_argument("--device", default="cuda:0", help="cpu: a smoke run (serial only)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    import warp as wp

    from vabench.sim_mjx.warp.device import warp_problem

    problem = warp_problem(args.device)
    if problem is not None:
        print(f"warp_streams needs a GPU: {problem}")
        return 2
    device = wp.get_device(args.device)
    wp.set_device(device)
    tasks = list(base_tasks())[: args.tasks]
    counts = sorted({min(int(c), len(tasks)) for c in args.counts.split(",")})
    print(f"device: {device.name}; {len(tasks)} families; substeps per action {args.substeps}")
    results = []
    for worlds in (int(w) for w in args.worlds.split(",")):
        t0 = time.perf_counter()
        batches = [build(t, worlds, args.settle) for t in tasks]
        print(f"{worlds} worlds: {len(batches)} batches built in {time.perf_counter() - t0:.1f} s")
        for n in counts:
            r = measure(batches[:n], worlds, args.substeps, args.repeats)
            results.append(r)
            s, c = r["serial"], r.get("streams")
            line = (
                f"  {n:3d} batches x {worlds:4d} worlds: serial {s['actions_per_s']:8.0f} "
                f"actions/s ({s['round_s'] * 1000:6.1f} ms/round)"
            )
            if c is not None:
                line += (
                    f", streams {c['actions_per_s']:8.0f} ({c['round_s'] * 1000:6.1f} ms), "
                    f"x{r['ratio']:.2f}; host queueing {c['queue_s'] * 1000:.1f} ms"
                )
            print(line)
        del batches
    if args.json:
        args.json.write_text(json.dumps({"device": device.name, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
