"""`python -m vabench.view RUN_DIR [--port P] [--host H]`: browse and annotate a run.

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

LOOPBACK = ("127.0.0.1", "localhost", "::1")


async def serve(viewer: Viewer, host: str, port: int) -> None:
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vabench.view",
        description="Browse a sweep's episodes and annotate the nine behavioural diagnostics.",
    )
    parser.add_argument("run_dir", type=Path, help="the sweep's run directory")
    parser.add_argument("--port", type=int, default=8765, help="port (0: any free port)")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback)")
    args = parser.parse_args(argv)
    if not 0 <= args.port <= 65535:
        parser.error(f"--port: {args.port} is not a port number (0-65535)")
    try:
        viewer = Viewer(args.run_dir)
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
