"""Rendering throughput: the worker pool against rendering each slot in the main process.

    python benchmarks/render_throughput.py [--sizes 640x480,1280x960] [--batches 1,8,64,256,1024]
        [--workers 1,2] [--platform auto] [--baseline-cap 64] [--json FILE]

For each image size and batch size B, one request of B images (a seed of place_single_cube
after its reset, cameras cycling through the head view and the five semantic views) goes to a
`RenderPool` of W workers; the baseline renders and encodes the same images one by one in this
process with the same renderer. Printed: images/s of both, their ratio, and per image the time
inside the workers spent drawing (incl. reading pixels back) and JPEG encoding. The baseline's
rate does not depend on B, so it is measured on at most `--baseline-cap` images.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from vabench.render import gl


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--sizes", default="640x480,1280x960")
    p.add_argument("--batches", default="1,8,64,256,1024")
    p.add_argument("--workers", default="1,2")
    p.add_argument("--platform", default="egl", choices=("egl", "osmesa"))
    p.add_argument("--baseline-cap", type=int, default=64)
    p.add_argument("--task", default="place_single_cube")
    p.add_argument("--json")
    args = p.parse_args()
    gl.configure(args.platform)

    from vabench.render import camera as cam
    from vabench.render.__main__ import reset_state
    from vabench.render.renderer import SceneRenderer, encode_jpeg
    from vabench.render.worker import ImageSettings, RenderItem, RenderPool
    from vabench.seeds import verified_seeds
    from vabench.tasks import REGISTRY

    task = REGISTRY[args.task]
    qpos, variant, gcs = reset_state(args.task, verified_seeds(args.task)[0], "c")
    poses = [cam.head_view(gcs, task.arms), *cam.passive_bundle(gcs, task.arms)]
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    batches = [int(b) for b in args.batches.split(",")]
    worker_counts = [int(w) for w in args.workers.split(",")]
    max_w, max_h = max(s[0] for s in sizes), max(s[1] for s in sizes)

    local = SceneRenderer(task, args.platform, max_w, max_h)
    print(f"main-process renderer: {local.gl_info}; cpus {os.cpu_count()}")
    rows = []
    for width, height in sizes:
        settings = ImageSettings(width, height, 95)
        n_base = min(args.baseline_cap, max(batches))
        local.render(qpos, variant, poses[0], width, height)  # warm up (compiles shaders)
        t_draw = t_enc = 0.0
        t0 = time.perf_counter()
        for i in range(n_base):
            a = time.perf_counter()
            rgb = local.render(qpos, variant, poses[i % len(poses)], width, height)
            b = time.perf_counter()
            encode_jpeg(rgb, settings.quality)
            t_draw += b - a
            t_enc += time.perf_counter() - b
        base_rate = n_base / (time.perf_counter() - t0)
        print(
            f"\n{width}x{height}: baseline one by one in the main process: {base_rate:.1f} img/s "
            f"(draw {1e3 * t_draw / n_base:.1f} ms + encode {1e3 * t_enc / n_base:.1f} ms "
            f"per image, {n_base} images)"
        )
        print(
            f"{'workers':>7} {'batch':>6} {'img/s':>8} {'x base':>7} {'draw ms':>8} "
            f"{'enc ms':>7} {'KB/img':>7}"
        )
        for n_workers in worker_counts:
            with RenderPool(
                workers=n_workers, platform=args.platform, max_size=(max_w, max_h), timeout_s=600
            ) as pool:
                pool.render(
                    args.task, [RenderItem(qpos, variant, poses[0])] * n_workers, settings
                )  # warm up every worker
                for batch in batches:
                    items = [RenderItem(qpos, variant, poses[i % len(poses)]) for i in range(batch)]
                    before = (pool.stats.render_s, pool.stats.encode_s)
                    t0 = time.perf_counter()
                    jpegs = pool.render(args.task, items, settings)
                    wall = time.perf_counter() - t0
                    draw = (pool.stats.render_s - before[0]) / batch
                    enc = (pool.stats.encode_s - before[1]) / batch
                    kb = sum(len(j) for j in jpegs) / batch / 1024
                    rate = batch / wall
                    row = dict(
                        width=width,
                        height=height,
                        workers=n_workers,
                        batch=batch,
                        images_per_s=rate,
                        baseline_images_per_s=base_rate,
                        ratio=rate / base_rate,
                        draw_ms=1e3 * draw,
                        encode_ms=1e3 * enc,
                        kb_per_image=kb,
                        platform=str(pool.gl_info),
                    )
                    rows.append(row)
                    print(
                        f"{n_workers:>7} {batch:>6} {rate:>8.1f} {rate / base_rate:>7.2f} "
                        f"{1e3 * draw:>8.1f} {1e3 * enc:>7.1f} {kb:>7.0f}"
                    )
    local.close()
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {"renderer": str(local.gl_info), "cpus": os.cpu_count(), "rows": rows}, f, indent=1
            )


if __name__ == "__main__":
    main()
