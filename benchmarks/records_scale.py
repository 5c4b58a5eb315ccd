"""Records at scale: what reads a run directory, timed on synthetic runs of growing size.

    python benchmarks/records_scale.py [--sizes 216,2160] [--root DIR] [--ops OP,...]
        [--json FILE]
    python benchmarks/records_scale.py --sizes 2160,20000,200000 --root /tmp/scale

Per size, a synthetic run (benchmarks/synthetic_runs.py: configs/all.yaml's shape, seed lists
stretched to the size, 90 % finished, 2 % of the scored episodes annotated; kept in --root and
reused by a later invocation), then each operation in a process of its own, so that its peak
resident memory (VmHWM) is its own:

    resume       what `python -m vabench.sweep CONFIG` decides before it runs an episode: the
                 config and plan, the run directory's check (plan.json), the progress tally,
                 the ledger (`Ledger.open`), orphans adopted and the pending episodes
    dry_run      `python -m vabench.sweep CONFIG --dry-run` (estimate, choices, finished count)
    report       `vabench.report.generate` (RUN_DIR/report/)
    diagnostics  `python -m vabench.diagnostics RUN_DIR` (the tables of the annotations)
    viewer       `vabench.view` on loopback: start (the index), then the run page as a browser
                 loads it, first byte and whole body of each request (`RUN_PAGE`), the same
                 after one more ledger line (a sweep still writing), and one episode's timeline
                 and annotation panel

Times are measured after the imports (which every size pays alike; `process_s` includes them).
The table gives each operation's seconds and peak RSS per size, and how each grows per 10x
episodes between consecutive sizes: (t2 / t1) ** (1 / log10(n2 / n1)); 10x is linear, 100x
quadratic. Speed targets (docs/PERFORMANCE.md, "Records at scale") are read off this table;
nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import contextlib
import http.client
import io
import itertools
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from synthetic_runs import SyntheticRun, make_run

OPS = ("resume", "dry_run", "report", "diagnostics", "viewer")
MARKER = "synthetic.json"
RUN_PAGE = ("/", "/api/run?offset=0&limit=500")
"""What the run page fetches when it opens (vabench/view/static/run.js): the HTML, then the
first page of episodes."""
KEEP = 4 << 20
"""Bytes of a response body kept to check (a whole run's listing is not)."""


def memory_mb(field: str = "VmHWM") -> float:
    """The process's resident memory (VmRSS) or its peak (VmHWM), in MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def synthetic(root: Path, size: int) -> SyntheticRun:
    """The synthetic run of `size` under root/<size>, made once."""
    where = root / str(size)
    marker = where / MARKER
    if marker.is_file():
        saved = json.loads(marker.read_text())
        return SyntheticRun(
            **{k: Path(v) if k in ("root", "config", "run_dir") else v for k, v in saved.items()}
        )
    if where.exists():
        import shutil

        shutil.rmtree(where)
    t0 = time.perf_counter()
    run = make_run(where, size)
    print(f"  generated {run.planned} episodes in {time.perf_counter() - t0:.0f} s", flush=True)
    marker.write_text(
        json.dumps({k: str(v) if isinstance(v, Path) else v for k, v in asdict(run).items()})
    )
    return run


# -- the operations ---------------------------------------------------------------------------


def op_resume(run: SyntheticRun) -> Callable[[], dict[str, Any]]:
    from vabench.config import load_config
    from vabench.config.choices import choose
    from vabench.sweep.display import Tally
    from vabench.sweep.plan import plan
    from vabench.sweep.rundir import check_run_dir
    from vabench.sweep.runner import LocalSweep

    def timed() -> dict[str, Any]:
        config = load_config(run.config)
        choices = choose(config)
        keys = plan(config)
        check_run_dir(run.run_dir, config, keys, config.document())
        status = Tally(run.run_dir, keys).status()
        sweep = LocalSweep(config, keys, run.run_dir, choices)
        sweep._adopt_orphans()
        pending = sweep._pending()
        return {"planned": len(keys), "finished": status.total().done, "pending": len(pending)}

    return timed


def op_dry_run(run: SyntheticRun) -> Callable[[], dict[str, Any]]:
    from vabench.sweep.__main__ import main

    def timed() -> dict[str, Any]:
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            rc = main([str(run.config), "--dry-run"])
        lines = out.getvalue().strip().splitlines()
        # what the dry run says the run directory holds (its output line; later lines add the
        # summary modes and the wall time)
        held = [line for line in lines if line.startswith("output: ")] or lines[-1:]
        return {"rc": rc, "output_line": held[0]}

    return timed


def op_report(run: SyntheticRun) -> Callable[[], dict[str, Any]]:
    from vabench.report import generate
    from vabench.report.build import task_arms

    task_arms()  # the task registry (JAX): an import, paid by every size alike

    def timed() -> dict[str, Any]:
        return {"files": len(generate(run.run_dir).files)}

    return timed


def op_diagnostics(run: SyntheticRun) -> Callable[[], dict[str, Any]]:
    from vabench.diagnostics import sections  # noqa: F401
    from vabench.diagnostics.__main__ import main
    from vabench.tables import section_markdown  # noqa: F401

    with contextlib.suppress(ImportError):  # what the agreement statistics import
        import scipy.stats  # noqa: F401
        import statsmodels.stats.inter_rater  # noqa: F401

    def timed() -> dict[str, Any]:
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main([str(run.run_dir)])
        return {"rc": rc, "chars": len(out.getvalue())}

    return timed


def _get(port: int, path: str) -> dict[str, Any]:
    """One request: seconds to the response's head (its first byte, as aiohttp sends a JSON
    body with its head) and to its last byte; the body is kept up to `KEEP` bytes."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=600)
    t0 = time.perf_counter()
    conn.request("GET", path)
    response = conn.getresponse()
    first = time.perf_counter() - t0
    size, kept = 0, []
    while chunk := response.read(1 << 16):
        size += len(chunk)
        if size <= KEEP:
            kept.append(chunk)
    full = time.perf_counter() - t0
    conn.close()
    return {
        "status": response.status,
        "first_byte_s": first,
        "full_s": full,
        "bytes": size,
        "body": b"".join(kept) if size <= KEEP else b"",
    }


def op_viewer(run: SyntheticRun) -> Callable[[], dict[str, Any]]:
    import asyncio
    import threading

    from aiohttp import web

    from vabench.diagnostics.episodes import task_instruction
    from vabench.run_layout import RunDir
    from vabench.view.app import Viewer

    task_instruction("grasp_single_cube")  # the task registry (JAX), as `op_report`

    def timed() -> dict[str, Any]:
        t0 = time.perf_counter()
        viewer = Viewer(run.run_dir)
        start_s = time.perf_counter() - t0
        loop = asyncio.new_event_loop()
        runner = web.AppRunner(viewer.app(), access_log=None)
        loop.run_until_complete(runner.setup())
        loop.run_until_complete(web.TCPSite(runner, "127.0.0.1", 0).start())
        port = runner.addresses[0][1]
        threading.Thread(target=loop.run_forever, daemon=True).start()

        def page() -> dict[str, Any]:
            gets = [_get(port, path) for path in RUN_PAGE]
            assert all(g["status"] == 200 for g in gets), [g["status"] for g in gets]
            return {
                "first_byte_s": max(g["first_byte_s"] for g in gets),
                "full_s": sum(g["full_s"] for g in gets),
                "bytes": sum(g["bytes"] for g in gets),
                "body": gets[-1]["body"],
            }

        cold = page()
        warm = page()
        # A sweep still writing: one more ledger line makes the next request read it.
        results = RunDir(run.run_dir).results
        size = results.stat().st_size
        with open(results, "rb") as f:
            line = f.readline()
        try:
            with open(results, "ab") as f:
                f.write(line.replace(b'"run": ', b'"run": 9', 1).replace(b"/run_", b"/run_9", 1))
            grown = page()
        finally:
            os.truncate(results, size)
        body = json.loads(cold["body"]) if cold["body"] else {}
        episodes = [
            json.loads(x)["episode_dir"].removeprefix("episodes/")
            for x in results.read_bytes()[:100_000].splitlines()[:2]
        ]
        _get(port, f"/api/episode?id={episodes[1]}")  # warm-up: the first timeline imports
        episode = _get(port, f"/api/episode?id={episodes[0]}")
        panel = _get(port, f"/api/annotations?episode={episodes[0]}&annotator=alice")
        loop.call_soon_threadsafe(loop.stop)
        return {
            "start_s": start_s,
            "page_first_byte_s": cold["first_byte_s"],
            "page_full_s": cold["full_s"],
            "page_bytes": cold["bytes"],
            "warm_first_byte_s": warm["first_byte_s"],
            "grown_first_byte_s": grown["first_byte_s"],
            "episode_s": episode["full_s"],
            "annotations_s": panel["full_s"],
            "total": body.get("total", len(body.get("episodes", []))),
            "statuses": [episode["status"], panel["status"]],
        }

    return timed


OPERATIONS = {
    "resume": op_resume,
    "dry_run": op_dry_run,
    "report": op_report,
    "diagnostics": op_diagnostics,
    "viewer": op_viewer,
}


def run_op(op: str, run: SyntheticRun) -> dict[str, Any]:
    """`op` in this process: its figures plus the memory after imports and at the peak."""
    import logging

    # The operations' own log lines are not the figures; put the process's setting back after
    # (in-process runs, the tests', share it with everything that runs later).
    previous = logging.root.manager.disable
    logging.disable(logging.INFO)
    try:
        timed = OPERATIONS[op](run)
        before = memory_mb("VmRSS")
        t0 = time.perf_counter()
        out: dict[str, Any] = {"op": op, **timed()}
        out["seconds"] = time.perf_counter() - t0
    finally:
        logging.disable(previous)
    out["base_rss_mb"] = before
    out["peak_rss_mb"] = memory_mb("VmHWM")
    return out


def run_isolated(op: str, run: SyntheticRun) -> dict[str, Any]:
    """`op` in a child process (this file with --child): its own peak memory."""
    marker = json.dumps({k: str(v) if isinstance(v, Path) else v for k, v in asdict(run).items()})
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, __file__, "--child", op, marker],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path[:2])},
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{op} failed:\n{proc.stderr[-4000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["process_s"] = time.perf_counter() - t0
    return out


def growth(rows: list[dict[str, Any]], key: str) -> list[str]:
    """Per consecutive sizes: how `key` grows per 10x episodes."""
    out = [""]
    for a, b in itertools.pairwise(rows):
        ta, tb = a.get(key), b.get(key)
        if not ta or not tb or a["planned"] == b["planned"]:
            out.append("")
            continue
        per10 = (tb / ta) ** (1 / math.log10(b["planned"] / a["planned"]))
        out.append(f"{per10:.1f}x")
    return out


def table(results: list[dict[str, Any]]) -> str:
    lines = [
        f"{'operation':<22}{'episodes':>10}{'seconds':>10}{'/10x':>7}{'peak MB':>10}"
        f"{'+MB':>8}{'/10x':>7}"
    ]
    for op in OPS:
        rows = [r for r in results if r["op"] == op]
        if not rows:
            continue
        names = [(op, "seconds")]
        if op == "viewer":
            names = [
                ("viewer start", "start_s"),
                ("run page first byte", "page_first_byte_s"),
                ("run page full", "page_full_s"),
                ("  after a new line", "grown_first_byte_s"),
                ("episode timeline", "episode_s"),
                ("annotation panel", "annotations_s"),
            ]
        for r in rows:
            r["added_mb"] = r["peak_rss_mb"] - r["base_rss_mb"]
        mem = growth(rows, "added_mb")
        for label, key in names:
            times = growth(rows, key)
            for i, r in enumerate(rows):
                lines.append(
                    f"{label:<22}{r['planned']:>10,}{r[key]:>10.2f}{times[i]:>7}"
                    f"{r['peak_rss_mb']:>10.0f}{r['added_mb']:>8.0f}{mem[i]:>7}"
                )
    return "\n".join(lines)


def measure(
    sizes: list[int], root: Path, ops: list[str], isolate: bool = True
) -> list[dict[str, Any]]:
    results = []
    for size in sizes:
        print(f"size {size}:", flush=True)
        run = synthetic(root, size)
        for op in ops:
            out = run_isolated(op, run) if isolate else run_op(op, run)
            out.update(planned=run.planned, finished=run.finished, annotated=run.annotated)
            print(f"  {op}: {out['seconds']:.2f} s, peak {out['peak_rss_mb']:.0f} MB", flush=True)
            results.append(out)
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="216,2160", help="planned episodes, comma-separated")
    p.add_argument("--root", type=Path, help="where the synthetic runs are kept (default: temp)")
    p.add_argument("--ops", default=",".join(OPS), help=f"of {', '.join(OPS)}")
    p.add_argument("--json", type=Path, help="write the figures here")
    p.add_argument(
        "--record",
        action="store_true",
        help="append the seconds to benchmarks/results/records.json",
    )
    p.add_argument("--child", nargs=2, metavar=("OP", "RUN"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        op, saved = args.child
        fields = json.loads(saved)
        run = SyntheticRun(
            **{k: Path(v) if k in ("root", "config", "run_dir") else v for k, v in fields.items()}
        )
        print(json.dumps(run_op(op, run), default=str))
        return 0
    ops = [o for o in args.ops.split(",") if o]
    unknown = [o for o in ops if o not in OPS]
    if unknown:
        p.error(f"--ops: unknown {unknown}; valid: {', '.join(OPS)}")
    sizes = sorted(int(s) for s in args.sizes.split(","))
    with contextlib.ExitStack() as stack:
        root = args.root
        if root is None:
            import tempfile

            root = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="records-scale-")))
        results = measure(sizes, root, ops)
    print()
    print(table(results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    if args.record:
        record_results(results)
    return 0


RECORDED = {
    "resume": "resume decision",
    "dry_run": "--dry-run",
    "report": "report",
    "diagnostics": "diagnostics summary",
}
"""The operations whose seconds `--record` keeps, by their figure's name."""


def record_results(results: list[dict[str, Any]]) -> None:
    """Each recorded operation's seconds as a dated record (benchmarks/results/records.json)."""
    import results_log

    for r in results:
        if r["op"] in RECORDED:
            results_log.append(
                "records",
                results_log.record(
                    f"{RECORDED[r['op']]}, {r['finished']:,} episodes",
                    round(r["seconds"], 3),
                    "s",
                    f"synthetic run directory; peak RSS {r['peak_rss_mb']:.0f} MB",
                ),
            )


if __name__ == "__main__":
    sys.exit(main())
