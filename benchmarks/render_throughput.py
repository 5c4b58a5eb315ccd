"""Rendering throughput: the Warp ray tracer against the GL worker pool, side by side in one run.

    python benchmarks/render_throughput.py [--sizes 640x480,1280x960] [--batches 1,64,256,1024]
        [--workers 4,8] [--slots 256] [--repeats 20] [--renderers gl,warp] [--json FILE]

Images as the engine consumes them: JPEG bytes (quality 95, 4:2:0) of a task's states after
their resets (the first verified seeds, cycled, so worlds differ), cameras cycling through the
head view and the five semantic views. For every image size:

1. throughput, images/s for a request of B images: the GL `RenderPool` with W workers (the
   best W is the baseline), the `WarpRenderPool` with JPEG on host threads (libjpeg-turbo), and
   with JPEG on the device (nvImageCodec, where installed), and on a GPU with JPEG in our own
   Warp kernels (`warp_jpeg`, the shipped default there); with the ratio of each Warp row to
   the best GL row of the same B;
2. latency of one step's images for `--slots` slots: the active protocol (one image per slot)
   and the passive bundle (five per slot), `--repeats` requests each, p50 and p95;
3. the split of a Warp request: ray tracing (incl. BVH refit and kinematics) vs JPEG.

Run it on a GPU host (`VABENCH_WARP_DEVICE` picks the device; `cpu` works, slowly, with small
sizes for a smoke check). Results go to docs/PERFORMANCE.md, "Renderer", with the device and date.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _states(task_name: str, n_seeds: int):
    from vabench.render import camera as cam
    from vabench.render.__main__ import reset_state
    from vabench.tasks import REGISTRY
    from vabench.tasks.manifests import verified_seeds

    arms = REGISTRY[task_name].arms
    out = []
    for seed in verified_seeds(task_name)[:n_seeds]:
        qpos, variant, gcs = reset_state(task_name, seed, "c")
        out.append((qpos, variant, [cam.head_view(gcs, arms), *cam.passive_bundle(gcs, arms)]))
    return out


def _items(states, n: int, passive: bool = False):
    from vabench.render.images import RenderItem

    items = []
    for i in range(n):
        qpos, variant, poses = states[i % len(states)]
        if passive:
            items.extend(RenderItem(qpos, variant, p) for p in poses[1:])
        else:
            items.append(RenderItem(qpos, variant, poses[i % len(poses)]))
    return items


def _timed(render, items, settings, repeats: int) -> list[float]:
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = render(items, settings)
        walls.append(time.perf_counter() - t0)
        assert len(out) == len(items)
    return walls


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--sizes", default="640x480,1280x960")
    p.add_argument("--batches", default="1,64,256,1024")
    p.add_argument("--workers", default="4,8", help="GL worker counts to try")
    p.add_argument("--renderers", default="gl,warp")
    p.add_argument(
        "--warp-jpeg",
        default="host,device,kernels",
        help="the Warp renderer's JPEG paths to time (host, device: nvJPEG/nvImageCodec, kernels)",
    )
    p.add_argument("--slots", type=int, default=256)
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--task", default="place_single_cube")
    p.add_argument("--json")
    args = p.parse_args()

    import warp as wp

    from vabench.render import gpu_jpeg
    from vabench.render.images import ImageSettings
    from vabench.render.warp_renderer import WarpRenderPool
    from vabench.render.worker import RenderPool

    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    batches = [int(b) for b in args.batches.split(",")]
    renderers = args.renderers.split(",")
    max_size = (max(s[0] for s in sizes), max(s[1] for s in sizes))
    states = _states(args.task, args.seeds)
    print(f"task {args.task}, {len(states)} distinct states; cpus {os.cpu_count()}")
    report: dict = {"task": args.task, "cpus": os.cpu_count(), "rows": [], "latency": []}

    variants: list[tuple[str, object]] = []
    if "gl" in renderers:
        for w in (int(x) for x in args.workers.split(",")):
            variants.append((f"gl x{w}", RenderPool(workers=w, max_size=max_size, timeout_s=900)))
    jpegs = args.warp_jpeg.split(",")
    if "warp" in renderers:
        if "host" in jpegs:
            variants.append(("warp, jpeg host", WarpRenderPool(max_size=max_size, jpeg="host")))
        if "device" in jpegs and gpu_jpeg.available():
            variants.append(("warp, jpeg device", WarpRenderPool(max_size=max_size, jpeg="device")))
        if "kernels" in jpegs and wp.is_cuda_available():  # the shipped default on a GPU
            pool = WarpRenderPool(max_size=max_size, jpeg="kernels")
            variants.append(("warp, jpeg kernels", pool))
    for name, pool in variants:
        info = pool.start()  # type: ignore[attr-defined]
        print(f"{name}: {info}")
        report.setdefault("renderers", {})[name] = str(info)

    for width, height in sizes:
        settings = ImageSettings(width, height, 95, "420")
        print(f"\n{width}x{height}, JPEG q95 4:2:0")
        print(
            f"{'renderer':<20} {'batch':>6} {'img/s':>9} {'x GL':>6} {'draw ms':>8} {'jpeg ms':>8}"
        )
        best_gl: dict[int, float] = {}
        for name, pool in variants:
            render = lambda items, s, pool=pool: pool.render(args.task, items, s)  # noqa: E731
            render(_items(states, 8), settings)  # warm up: contexts, kernels, shaders
            for batch in batches:
                items = _items(states, batch)
                stats = pool.stats  # type: ignore[attr-defined]
                before = (stats.render_s, stats.encode_s)
                reps = max(1, min(5, 2048 // batch))
                walls = _timed(render, items, settings, reps)
                rate = batch / float(np.median(walls))
                draw = 1e3 * (stats.render_s - before[0]) / (reps * batch)
                enc = 1e3 * (stats.encode_s - before[1]) / (reps * batch)
                if name.startswith("gl"):
                    best_gl[batch] = max(best_gl.get(batch, 0.0), rate)
                ratio = rate / best_gl[batch] if best_gl.get(batch) else float("nan")
                report["rows"].append(
                    dict(
                        renderer=name,
                        width=width,
                        height=height,
                        batch=batch,
                        images_per_s=rate,
                        x_gl=ratio,
                        draw_ms=draw,
                        encode_ms=enc,
                    )
                )
                print(f"{name:<20} {batch:>6} {rate:>9.1f} {ratio:>6.2f} {draw:>8.3f} {enc:>8.3f}")
        print(f"\nlatency of one step's images, {args.slots} slots ({args.repeats} requests)")
        print(f"{'renderer':<20} {'protocol':>8} {'images':>7} {'p50 ms':>8} {'p95 ms':>8}")
        for name, pool in variants:
            render = lambda items, s, pool=pool: pool.render(args.task, items, s)  # noqa: E731
            for protocol in ("active", "passive"):
                items = _items(states, args.slots, passive=protocol == "passive")
                walls = 1e3 * np.array(_timed(render, items, settings, args.repeats))
                p50, p95 = np.percentile(walls, [50, 95])
                report["latency"].append(
                    dict(
                        renderer=name,
                        width=width,
                        height=height,
                        protocol=protocol,
                        slots=args.slots,
                        images=len(items),
                        p50_ms=p50,
                        p95_ms=p95,
                    )
                )
                print(f"{name:<20} {protocol:>8} {len(items):>7} {p50:>8.1f} {p95:>8.1f}")
    for _, pool in variants:
        pool.close()  # type: ignore[attr-defined]
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
