"""Look at what a model sees.

    python -m vabench.render snapshot --task T --seed S [--view V | --passive] --out DIR
    python -m vabench.render sheet --out FILE.png [--tasks a,b] [--size 320x240]
    python -m vabench.render parity --out FILE.png [--tasks a,b] [--size 320x240]

`snapshot` resets the seed (C MuJoCo by default, as the seeds were screened) and writes the
JPEGs a model would receive at reset: the head view "center_high", one semantic view, or the
five-view passive bundle in its fixed order (files numbered in that order); `--debug` adds
debug_*.jpg beside them for people (contact points, GC markers, site frames, a label).
`sheet` writes one contact sheet for people: every base task at its first retained seed, in
the head view and the five semantic views, with labels on the sheet (never on model images).
`parity` puts the GL and the Warp renderer side by side: per task a GL row and a Warp row of
the same six views, and prints the mean absolute difference of every image (grey levels).
`--renderer` picks the renderer of `snapshot` and `sheet` (auto: Warp where it can run).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from vabench.render import camera as cam
from vabench.render.backends import make_renderer
from vabench.render.debug import DebugOverlays
from vabench.render.images import ImageSettings, RenderError, RenderItem
from vabench.render.worker import RenderPool
from vabench.sim_mjx.backends import BackendUnavailable


def reset_state(task_name: str, seed: int, backend: str) -> tuple[np.ndarray, int, dict]:
    """qpos, object model id and per-arm GC of one seed right after its reset."""
    from vabench.tasks import REGISTRY
    from vabench.tasks.task_batch import TaskBatch

    task = REGISTRY[task_name]
    tb = TaskBatch(task, 1, backend=backend)
    report = tb.reset([0], [seed])[0]
    if not report.ok:
        raise SystemExit(f"{task_name} seed {seed} fails its reset: {report.reason}")
    view = tb.views([0])[0]
    gcs = {arm: view.arms[arm].gc for arm in task.arms}
    return np.asarray(tb.batch.qpos()[0]), int(tb.batch.variant()[0]), gcs


def _views(arms: Sequence[str], gcs: dict, view: str | None, passive: bool) -> list[cam.CameraPose]:
    if passive:
        return cam.passive_bundle(gcs, arms)
    if view is None or view == cam.HEAD_VIEW:
        return [cam.head_view(gcs, arms)]
    return [cam.apply_camera_action(cam.head_view(gcs, arms), f"view_{view}", gcs, arms)]


def snapshot(args: argparse.Namespace) -> None:
    from vabench.tasks import REGISTRY

    if args.task not in REGISTRY:
        raise SystemExit(f"unknown task {args.task!r}; tasks: {sorted(REGISTRY)}")
    arms = REGISTRY[args.task].arms
    renderer, choice = make_renderer(args.renderer, workers=1, platform=args.platform)
    qpos, variant, gcs = reset_state(args.task, args.seed, args.backend)
    poses = _views(arms, gcs, args.view, args.passive)
    settings = ImageSettings(args.width, args.height, args.quality)
    items = [RenderItem(qpos, variant, p) for p in poses]
    with contextlib.closing(renderer):
        print(f"renderer: {renderer.start()} ({choice.reason})", file=sys.stderr)
        jpegs = renderer.render(args.task, items, settings)
    debug = []
    if args.debug:  # for people: same views with contacts, GC markers, frames and a label
        with RenderPool(workers=1, platform=args.platform) as pool:
            debug = [
                pool.render_debug(
                    args.task,
                    [item],
                    DebugOverlays(
                        contacts=True,
                        gc_markers=True,
                        frames=True,
                        label=f"{args.task} seed {args.seed} {item.camera.label}",
                    ),
                    settings,
                )[0]
                for item in items
            ]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for i, (pose, jpeg) in enumerate(zip(poses, jpegs, strict=True)):
        name = (
            f"{args.task}_seed{args.seed}_{i}_{pose.label}.jpg"
            if args.passive
            else (f"{args.task}_seed{args.seed}_{pose.label}.jpg")
        )
        (out / name).write_bytes(jpeg)
        print(out / name)
        if debug:
            (out / f"debug_{name}").write_bytes(debug[i])
            print(out / f"debug_{name}")


class ContactSheet:
    """A grid for people: a header of view names, a label per row, thumbnails (never a model
    image: labels go on the sheet only)."""

    LABEL_W, HEADER_H = 190, 24
    COLUMNS = (cam.HEAD_VIEW, *cam.VIEWS)

    def __init__(self, n_rows: int, thumb: str):
        self.tw, self.th = (int(v) for v in thumb.split("x"))
        size = (self.LABEL_W + self.tw * len(self.COLUMNS), self.HEADER_H + self.th * n_rows)
        self.image = Image.new("RGB", size, "white")
        self.draw = ImageDraw.Draw(self.image)
        for c, name in enumerate(self.COLUMNS):
            self.draw.text((self.LABEL_W + c * self.tw + 6, 6), name, fill=(0, 0, 0))

    def row(self, r: int, label: str, frames: Sequence[np.ndarray]) -> None:
        y = self.HEADER_H + r * self.th
        self.draw.text((6, y + 6), label, fill=(0, 0, 0))
        for c, rgb in enumerate(frames):
            thumb = Image.fromarray(np.asarray(rgb)).resize((self.tw, self.th))
            self.image.paste(thumb, (self.LABEL_W + c * self.tw, y))

    def save(self, path: str) -> None:
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        self.image.save(out)
        print(out)


def _tasks(names: list[str]) -> list[str]:
    from vabench.tasks import REGISTRY

    unknown = sorted(set(names) - set(REGISTRY))
    if unknown:
        raise SystemExit(f"unknown tasks {unknown}; tasks: {sorted(REGISTRY)}")
    return names


def _first_seed_items(task_name: str, backend: str) -> tuple[int, list[RenderItem]]:
    """The head view and the five views of a task's first verified seed after its reset."""
    from vabench.tasks import REGISTRY
    from vabench.tasks.manifests import verified_seeds

    arms = REGISTRY[task_name].arms
    seed = verified_seeds(task_name)[0]
    qpos, variant, gcs = reset_state(task_name, seed, backend)
    poses = [cam.head_view(gcs, arms), *cam.passive_bundle(gcs, arms)]
    return seed, [RenderItem(qpos, variant, p) for p in poses]


def sheet(args: argparse.Namespace) -> None:
    from vabench.tasks import BASE_FAMILIES

    tasks = _tasks(args.tasks.split(",") if args.tasks else list(BASE_FAMILIES))
    grid = ContactSheet(len(tasks), args.size)
    settings = ImageSettings(args.width, args.height, args.quality)
    pool, choice = make_renderer(args.renderer, workers=args.workers, platform=args.platform)
    with contextlib.closing(pool):
        print(f"renderer: {pool.start()} ({choice.reason})", file=sys.stderr)
        for r, task_name in enumerate(tasks):
            seed, items = _first_seed_items(task_name, args.backend)
            jpegs = pool.render(task_name, items, settings)
            grid.row(r, f"{task_name}\nseed {seed}", [_decode(j) for j in jpegs])
            print(f"{task_name}: seed {seed}", file=sys.stderr)
    grid.save(args.out)


def parity(args: argparse.Namespace) -> None:
    from vabench.render.warp_renderer import WarpRenderPool

    tasks = _tasks(args.tasks.split(","))
    grid = ContactSheet(2 * len(tasks), args.size)
    settings = ImageSettings(args.width, args.height, 100, "444")  # compare pixels, not JPEG
    size = (args.width, args.height)
    with (
        RenderPool(workers=1, platform=args.platform, max_size=size) as gl_pool,
        WarpRenderPool(max_size=size) as warp_pool,
    ):
        print(f"renderers: {gl_pool.gl_info} | {warp_pool.info}", file=sys.stderr)
        for r, task_name in enumerate(tasks):
            seed, items = _first_seed_items(task_name, args.backend)
            gl_rgb = [_decode(j) for j in gl_pool.render(task_name, items, settings)]
            warp_rgb = list(warp_pool.render_rgb(task_name, items, settings))
            gaps = [
                float(np.abs(g.astype(int) - w).mean())
                for g, w in zip(gl_rgb, warp_rgb, strict=True)
            ]
            print(
                f"{task_name} seed {seed}: mean |GL - Warp| per view: "
                + ", ".join(f"{c} {d:.2f}" for c, d in zip(grid.COLUMNS, gaps, strict=True))
            )
            grid.row(2 * r, f"{task_name}\nseed {seed}\nGL", gl_rgb)
            grid.row(2 * r + 1, f"{task_name}\nseed {seed}\nWarp", warp_rgb)
    grid.save(args.out)


def _decode(jpeg: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"))


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m vabench.render",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("--backend", choices=("c", "warp", "mjx"), default="c", help="physics")
        p.add_argument("--renderer", choices=("auto", "warp", "gl"), default="auto")
        p.add_argument("--platform", choices=("auto", "egl", "osmesa"), default="auto")
        p.add_argument("--width", type=int, default=1280)
        p.add_argument("--height", type=int, default=960)
        p.add_argument("--quality", type=int, default=95)

    snap = sub.add_parser("snapshot", help="the images a model gets at reset")
    snap.add_argument("--task", required=True)
    snap.add_argument("--seed", type=int, required=True)
    group = snap.add_mutually_exclusive_group()
    group.add_argument("--view", choices=[cam.HEAD_VIEW, *cam.VIEWS])
    group.add_argument("--passive", action="store_true", help="the five-view bundle")
    snap.add_argument("--out", required=True)
    snap.add_argument(
        "--debug",
        action="store_true",
        help="also write debug_*.jpg with overlays (never what a model sees)",
    )
    common(snap)
    snap.set_defaults(run=snapshot)

    sh = sub.add_parser("sheet", help="every task in the head view and the five views")
    sh.add_argument("--out", required=True)
    sh.add_argument("--tasks", help="comma-separated task names (default: the 14 base tasks)")
    sh.add_argument("--size", default="320x240", help="thumbnail size WxH")
    sh.add_argument("--workers", type=int, default=2)
    common(sh)
    sh.set_defaults(run=sheet)

    par = sub.add_parser("parity", help="GL and Warp images of the same views side by side")
    par.add_argument("--out", required=True)
    par.add_argument("--tasks", default="place_single_cube,place_shoe")
    par.add_argument("--size", default="320x240", help="thumbnail size WxH")
    common(par)
    par.set_defaults(run=parity)

    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        args.run(args)
    except (BackendUnavailable, RenderError) as err:
        raise SystemExit(f"error: {err}") from None


if __name__ == "__main__":
    main()
