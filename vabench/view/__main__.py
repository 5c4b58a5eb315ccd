"""`python -m vabench.view PATH [--port P] [--host H]`: browse and annotate a run.

PATH is a run directory, or a directory of runs (`vabench.view.runs`: a run list, runs
compared side by side). `--bundle DIR` writes one run as a static site instead of serving it
(`vabench.view.bundle`).

Binds 127.0.0.1 unless `--host` says otherwise: the annotation endpoints have no login, so a
wider bind is for a trusted network only (a warning says so)."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

from aiohttp import web

from vabench.diagnostics.episodes import RunDirError
from vabench.view.app import Viewer
from vabench.view.bundle import BundleError, write_bundle
from vabench.view.runs import RunsViewer, is_run

LOOPBACK = ("127.0.0.1", "localhost", "::1")


async def serve(viewer: Viewer | RunsViewer, host: str, port: int) -> None:
    runner = web.AppRunner(viewer.app(), access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    await site.start()
    bound = runner.addresses[0]
    shown = f"[{bound[0]}]" if ":" in str(bound[0]) else bound[0]
    print(f"serving {viewer.run_dir} at http://{shown}:{bound[1]}/  (Ctrl-C stops)", flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        await runner.cleanup()


def open_path(path: Path) -> Viewer | RunsViewer:
    """The viewer of a run directory, or of a directory of runs (`RunDirError` if neither)."""
    if is_run(path) or not path.is_dir():
        return Viewer(path)
    return RunsViewer(path)


def bundle(run_dir: Path, out: Path) -> int:
    if run_dir.is_dir() and not is_run(run_dir):
        print(f"error: --bundle: {run_dir} is no run directory (give one run)", file=sys.stderr)
        return 2
    try:
        n = write_bundle(run_dir, out)
    except (RunDirError, BundleError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {n:,} episodes: open {out / 'index.html'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vabench.view",
        description="Browse a sweep's episodes and annotate the nine behavioural diagnostics.",
    )
    parser.add_argument(
        "run_dir", type=Path, help="the sweep's run directory, or a directory of runs"
    )
    parser.add_argument("--port", type=int, default=8765, help="port (0: any free port)")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback)")
    parser.add_argument(
        "--bundle",
        type=Path,
        metavar="DIR",
        help="write the run as static pages into DIR (opens from disk) instead of serving it",
    )
    args = parser.parse_args(argv)
    if args.bundle is not None:
        return bundle(args.run_dir, args.bundle)
    if not 0 <= args.port <= 65535:
        parser.error(f"--port: {args.port} is not a port number (0-65535)")
    try:
        viewer = open_path(args.run_dir)
    except RunDirError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.host not in LOOPBACK:
        print(
            f"warning: binding {args.host}: anyone who can reach it can read the run and "
            "write annotations",
            file=sys.stderr,
        )
    try:
        asyncio.run(serve(viewer, args.host, args.port))
    except OSError as err:
        print(
            f"error: cannot listen on {args.host}:{args.port}: {err.strerror or err}",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
