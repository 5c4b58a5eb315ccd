"""Do several task batches step faster together on one GPU than one after the other?

    python benchmarks/warp_streams.py [--tasks 14] [--worlds 30,150] [--substeps 200] [--json OUT]

Why: on an H100 one action of a Warp batch takes ~90 ms whatever its size up to 256 slots
(docs/PERFORMANCE.md, "Simulator throughput"): MuJoCo Warp's kernels over a few dozen worlds
occupy a few of the GPU's 132 SMs, and an action is 200 substeps of ~100 small kernels each. A
sweep runs one batch per task family and track (dozens); today every batch of a process queues
its work on the device's one stream under the device lock, so they run one after the other, and
the processes executor's 16 CUDA contexts time-slice the GPU (one context at a time). This
measures what one process would gain by giving each batch its own CUDA stream: the same captured
substep graphs, launched

- serial: every batch's action on one stream, batch after batch (today's layout);
- streams: each batch on its own stream, the launches interleaved substep by substep, one
  synchronisation at the end (what a stream per WarpBatch would do);

- threads: each batch on its own stream AND its own host thread (what a batch whose lock is
  held only while it queues would allow: do launches of several threads overlap?);

each with graphs of K substeps (`--chunks`: 1 is today's graph per substep; a graph per
waypoint or per action queues fewer, longer graphs: what does capturing them cost, and does
the host queue them faster?), and prints agent actions per second (worlds x batches per round /
seconds per round), the ratio to serial with K = 1, the host time spent queueing the launches
(the lock would be held that long) and the capture time of each K.
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


def build(task, worlds: int, settle: int = 200, chunks: tuple[int, ...] = (1,)):
    """(model, data, {K: graph of K steps}, stream, {K: capture seconds}) of one family's scene
    on the GPU."""
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
    graphs, capture_s = {}, {}
    with wp.ScopedStream(stream) if stream else contextlib.nullcontext():
        mjw.step(m, d)  # loads the modules before capture
        for k in chunks:
            t0 = time.perf_counter()
            with wp.ScopedCapture(stream=stream) as capture:
                for _ in range(k):
                    mjw.step(m, d)
            graphs[k] = capture.graph
            wp.capture_launch(graphs[k], stream=stream)  # instantiates it
            wp.synchronize_device()
            capture_s[k] = time.perf_counter() - t0
        for _ in range(settle):  # contacts as in an episode
            wp.capture_launch(graphs[1] if 1 in graphs else graphs[chunks[0]], stream=stream)
    wp.synchronize_device()
    return m, d, graphs, stream, capture_s


def round_serial(batches, substeps: int, k: int) -> tuple[float, float]:
    import warp as wp

    one = batches[0][3]
    t0 = time.perf_counter()
    for _, _, graphs, _, _ in batches:
        for _ in range(substeps // k):
            wp.capture_launch(graphs[k], stream=one)
    queued = time.perf_counter() - t0
    wp.synchronize_device()
    return time.perf_counter() - t0, queued


def round_streams(batches, substeps: int, k: int) -> tuple[float, float]:
    import warp as wp

    t0 = time.perf_counter()
    for _ in range(substeps // k):
        for _, _, graphs, stream, _ in batches:
            wp.capture_launch(graphs[k], stream=stream)
    queued = time.perf_counter() - t0
    wp.synchronize_device()
    return time.perf_counter() - t0, queued


def round_threads(batches, substeps: int, k: int) -> tuple[float, float]:
    """Each batch queued and waited for by a thread of its own (Warp's launches and waits
    release the GIL); queue_s is the longest any thread spent queueing."""
    import threading

    import warp as wp

    queued = [0.0] * len(batches)
    start = threading.Barrier(len(batches) + 1)

    def one(i: int) -> None:
        _, _, graphs, stream, _ = batches[i]
        start.wait()
        t = time.perf_counter()
        for _ in range(substeps // k):
            wp.capture_launch(graphs[k], stream=stream)
        queued[i] = time.perf_counter() - t
        wp.synchronize_stream(stream)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(batches))]
    for t in threads:
        t.start()
    start.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    return time.perf_counter() - t0, max(queued)


MODES = {"serial": round_serial, "streams": round_streams, "threads": round_threads}


def measure(batches, worlds: int, substeps: int, repeats: int, chunks) -> dict:
    out: dict = {"batches": len(batches), "worlds": worlds, "modes": {}}
    on_gpu = batches[0][3] is not None  # streams exist on CUDA devices only
    for k in chunks:
        for name, fn in MODES.items():
            if name != "serial" and not on_gpu:
                continue
            fn(batches, substeps, k)  # warm
            times = [fn(batches, substeps, k) for _ in range(repeats)]
            wall = float(np.median([t for t, _ in times]))
            out["modes"][f"{name}/k{k}"] = {
                "round_s": wall,
                "queue_s": float(np.median([q for _, q in times])),
                "actions_per_s": len(batches) * worlds / wall,
            }
    base = out["modes"][f"serial/k{chunks[0]}"]["actions_per_s"]
    for r in out["modes"].values():
        r["ratio"] = r["actions_per_s"] / base
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", type=int, default=14, help="base families, one batch each")
    ap.add_argument("--counts", default="1,4,14", help="batches stepped together")
    ap.add_argument("--worlds", default="30,150", help="slots per batch")
    ap.add_argument("--substeps", type=int, default=200, help="physics steps of one action")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--settle", type=int, default=200, help="steps before timing")
    ap.add_argument("--chunks", default="1,10,50,200", help="substeps per captured graph")
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
    chunks = tuple(int(c) for c in args.chunks.split(","))
    if any(args.substeps % k for k in chunks):
        ap.error(f"every chunk must divide --substeps {args.substeps}")
    results = []
    for worlds in (int(w) for w in args.worlds.split(",")):
        t0 = time.perf_counter()
        batches = [build(t, worlds, args.settle, chunks) for t in tasks]
        print(f"{worlds} worlds: {len(batches)} batches built in {time.perf_counter() - t0:.1f} s")
        capture = {k: float(np.median([b[4][k] for b in batches])) for k in chunks}
        print(
            "  capture + first launch per graph: "
            + ", ".join(f"K={k} {capture[k]:.2f} s" for k in chunks)
        )
        for n in counts:
            r = measure(batches[:n], worlds, args.substeps, args.repeats, chunks)
            r["capture_s"] = capture
            results.append(r)
            for mode, m in r["modes"].items():
                print(
                    f"  {n:3d} batches x {worlds:4d} worlds {mode:12s} {m['actions_per_s']:8.0f} "
                    f"actions/s ({m['round_s'] * 1000:7.1f} ms/round, host queueing "
                    f"{m['queue_s'] * 1000:7.1f} ms) x{m['ratio']:.2f}"
                )
        del batches
    if args.json:
        args.json.write_text(json.dumps({"device": device.name, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
