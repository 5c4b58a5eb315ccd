"""The render megakernel's options side by side: GPU milliseconds a pass, and what each changes.

    python benchmarks/render_options.py [--tasks put_everything_in_basket,place_shoe]
        [--size 1280x960] [--worlds 24] [--repeats 10]
        [--options default,block128,block256,posed,posed+block256,nocull,noshadow,notex,default]
        [--json FILE]

One pass of MuJoCo Warp's batch ray tracer (`mjw.render`) over `--worlds` worlds of a task, each
world a different verified seed's reset state seen through one of the six views (head view and
the five semantic ones), timed alone on the device (median of `--repeats`, after two untimed
passes), for each option set, with the share of pixels that differ from the first set's image
(and by more than 2 grey levels, and the largest difference). Options, joined by `+`:

- `default`: MuJoCo Warp's defaults as `vabench.render.warp_pass` used them before 2026-11-27
  (block of 64 threads, scene BVH built at qpos0 and refit);
- `blockN`: N threads a block of the megakernel (`Model.block_dim.render`);
- `posed`: the scene BVH built again around a real scene (another seed's reset), then refit,
  as `RenderPass` does on its first draw;
- `shipped`: what `RenderPass` ships (`posed` + `RENDER_BLOCK_DIM`);
- `nocull`, `noshadow`, `notex`: backface culling, ray-cast shadows, textures off (these change
  what an image shows; measured to know their price, not shipped).

Run it on the GPU (`bash benchmarks/gpu/run.sh render_options`); `--device cpu` works for a
smoke check at small sizes. Results: docs/PERFORMANCE.md, "Renderer", with the device and date.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _scene(task, model, worlds: int):
    """(qpos, camera pos, rot, fovy) of `worlds` worlds: seeds' resets, the six views in turn."""
    import mujoco

    from vabench.render.camera import VIEWS, default_target, head_view, semantic_view
    from vabench.tasks.manifests import verified_seeds

    seeds = verified_seeds(task.name)
    rows = []
    for w in range(worlds):
        q = task.initial_qpos(model, seeds[w % len(seeds)])
        d = mujoco.MjData(model)
        d.qpos[:] = q
        mujoco.mj_kinematics(model, d)
        gcs = {}
        for arm in task.arms:
            pads = [
                d.site_xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"{arm}_pad_{s}")]
                for s in "ab"
            ]
            gcs[arm] = (pads[0] + pads[1]) / 2
        k = w % 6
        view = (
            head_view(gcs, task.arms)
            if k == 0
            else semantic_view(VIEWS[k - 1], gcs, default_target(task.arms))
        )
        rows.append((np.asarray(q, np.float32), view.pos, view.rot, view.fovy))
    return rows


def _pass(model, rows, width: int, height: int, options: set[str], posed_qpos):
    import mujoco
    import mujoco_warp as mjw
    import warp as wp

    from vabench.render.renderer import VIEW_CAMERA
    from vabench.render.warp_pass import RENDER_BLOCK_DIM, rebuild_scene_bvh, render_context

    if "shipped" in options:
        options = options | {"posed", f"block{RENDER_BLOCK_DIM}"}
    n = len(rows)
    m = mjw.put_model(model)
    d = mjw.make_data(model, nworld=n, nconmax=1, njmax=1)
    rc = render_context(
        model,
        n,
        width,
        height,
        use_textures="notex" not in options,
        use_shadows="noshadow" not in options,
        enable_backface_culling="nocull" not in options,
    )
    for o in options:
        if o.startswith("block"):
            m.block_dim.render = int(o[len("block") :])
    if "posed" in options:
        d.qpos.assign(np.tile(posed_qpos, (n, 1)))
        mjw.kinematics(m, d)
        mjw.refit_bvh(m, d, rc)
        rebuild_scene_bvh(rc, n)
    d.qpos.assign(np.stack([r[0] for r in rows]))
    mjw.kinematics(m, d)
    mjw.camlight(m, d)
    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, VIEW_CAMERA)
    xpos, xmat = d.cam_xpos.numpy(), d.cam_xmat.numpy()
    fovy = np.tile(m.cam_fovy.numpy()[:1], (n, 1))
    for i, (_, pos, rot, fov) in enumerate(rows):
        xpos[i, cam], xmat[i, cam], fovy[i, cam] = pos, rot, fov
    d.cam_xpos.assign(xpos)
    d.cam_xmat.assign(xmat)
    m.cam_fovy = wp.array(fovy, dtype=float)
    mjw.refit_bvh(m, d, rc)
    return m, d, rc


def measure(task_name: str, width: int, height: int, worlds: int, option_sets, repeats: int):
    import mujoco_warp as mjw
    import warp as wp

    from vabench.render.camera import FAR, NEAR
    from vabench.render.renderer import render_spec
    from vabench.tasks import get_task
    from vabench.tasks.manifests import verified_seeds

    task = get_task(task_name)
    model = render_spec(task, 0, width, height).compile()
    model.vis.map.znear = NEAR / model.stat.extent
    model.vis.map.zfar = FAR / model.stat.extent
    rows = _scene(task, model, worlds)
    posed = np.asarray(task.initial_qpos(model, verified_seeds(task_name)[-1]), np.float32)
    reference, out = None, []
    for spec in option_sets:
        m, d, rc = _pass(model, rows, width, height, set(spec.split("+")), posed)
        for _ in range(2):  # compile, warm up
            mjw.render(m, d, rc)
        wp.synchronize()
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            mjw.render(m, d, rc)
            wp.synchronize()
            times.append(time.perf_counter() - start)
        packed = rc.rgb_data.numpy()
        rgb = np.stack([(packed >> s) & 255 for s in (16, 8, 0)], -1).astype(np.int16)
        reference = rgb if reference is None else reference
        diff = np.abs(rgb - reference).max(-1)
        ms = statistics.median(times) * 1e3
        row = {
            "task": task_name,
            "options": spec,
            "ms_pass": round(ms, 3),
            "ms_image": round(ms / worlds, 4),
            "pixels_changed": float((diff > 0).mean()),
            "pixels_changed_over_2": float((diff > 2).mean()),
            "largest_difference": int(diff.max()),
        }
        out.append(row)
        print(
            f"{task_name:28s} {spec:22s} {ms:8.2f} ms a pass {ms / worlds:7.3f} ms an image   "
            f"pixels changed {row['pixels_changed']:.2e} (>2: {row['pixels_changed_over_2']:.2e}, "
            f"largest {row['largest_difference']})",
            flush=True,
        )
        del rc
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--tasks", default="put_everything_in_basket,place_shoe,grasp_single_cube")
    p.add_argument("--size", default="1280x960")
    p.add_argument("--worlds", type=int, default=24)
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument(
        "--options",
        default="default,block128,block256,posed,shipped,nocull,noshadow,notex,default",
        help="option sets, comma-separated; the first is the reference image",
    )
    p.add_argument("--device", default=None, help="a Warp device (default: Warp's)")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    wp.init()
    if args.device:
        wp.set_device(args.device)
    width, height = (int(v) for v in args.size.split("x"))
    print(f"device {wp.get_device()}; {args.size}; {args.worlds} worlds a pass", flush=True)
    rows = []
    for task in args.tasks.split(","):
        rows += measure(task, width, height, args.worlds, args.options.split(","), args.repeats)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
