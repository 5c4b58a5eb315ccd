"""python -m vabench.demos build [--task T ...] [--out DIR] [--manifests DIR] [--force]"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from vabench.demos import build, store
from vabench.render.worker import ImageSettings, RenderPool
from vabench.tasks import REGISTRY, base_tasks

# Manifest fields that decide the frames' bytes; with all equal, the hash must be equal too.
_INPUTS = ("demo_seed", "width", "height", "quality", "fps", "renderer")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vabench.demos")
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="build (or find current) the demonstration videos")
    b.add_argument("--task", action="append", help="a family (repeatable); default: all base")
    b.add_argument(
        "--out", type=Path, default=None, help="cache directory (default: ~/.cache/vabench/demos)"
    )
    b.add_argument("--manifests", type=Path, default=store.MANIFEST_DIR)
    b.add_argument("--width", type=int, default=build.DEMO_SETTINGS.width)
    b.add_argument("--height", type=int, default=build.DEMO_SETTINGS.height)
    b.add_argument("--quality", type=int, default=build.DEMO_SETTINGS.quality)
    b.add_argument("--force", action="store_true", help="rebuild even when the cache is current")
    b.add_argument("--no-mp4", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    names = args.task or [t.name for t in base_tasks()]
    for name in names:
        if name not in REGISTRY:
            parser.error(f"--task: unknown task {name!r}; valid tasks: {sorted(REGISTRY)}")
    try:
        settings = ImageSettings(args.width, args.height, args.quality)
    except ValueError as err:
        parser.error(str(err))
    with RenderPool(workers=1, max_size=(settings.width, settings.height)) as pool:
        for name in names:
            t0 = time.perf_counter()
            info = build.build_demo(
                name, args.out, settings=settings, pool=pool, force=args.force, mp4=not args.no_mp4
            )
            old = store.read_manifest(name, args.manifests)
            doc = store.manifest_doc(info, build.CANDIDATES_RULE)
            if old and all(old[k] == doc[k] for k in _INPUTS) and old["sha256"] != doc["sha256"]:
                print(f"{name}: frames differ from the committed manifest", file=sys.stderr)
            path = store.write_manifest(doc, args.manifests)
            print(
                f"{name}: seed {info.seed}, {info.n_frames} frames at {info.fps:g} fps "
                f"({info.width}x{info.height}) in {time.perf_counter() - t0:.1f} s -> {path}",
                file=sys.stderr,
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
