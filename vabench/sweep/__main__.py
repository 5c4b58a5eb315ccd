"""`python -m vabench.sweep CONFIG [--dry-run] [--out DIR] [--no-report]` (see vabench.sweep).

Running the same command again resumes: finished episodes are never re-run, interrupted ones
start again, infrastructure failures get their retry rounds. Exit code 0 when every planned
episode is in results.jsonl, 1 when some ended unscored (listed), 2 for a bad config, a run
directory of another plan, or an endpoint that refused the sweep's requests (a wrong key, an
unknown model: the sweep stops at once, naming the model and what to check).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from vabench.config import SweepConfigError, load_config
from vabench.sweep.display import Display
from vabench.sweep.plan import estimate, format_estimate, plan
from vabench.sweep.results import Ledger, LedgerError, ledger_key
from vabench.sweep.rundir import RunDirMismatch, check_run_dir
from vabench.sweep.runner import LocalSweep, SweepStopped

log = logging.getLogger("vabench.sweep")


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m vabench.sweep",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("config", type=Path)
    p.add_argument(
        "--dry-run", action="store_true", help="print the plan and its cost; run nothing"
    )
    p.add_argument("--out", help="run directory (default: the config's out)")
    p.add_argument("--no-report", action="store_true")
    p.add_argument("--plain", action="store_true", help="log lines instead of a live table")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    try:
        config = load_config(args.config, overrides={"out": args.out} if args.out else None)
    except SweepConfigError as err:
        print(err, file=sys.stderr)
        return 2
    keys = plan(config)
    run_dir = Path(config.out)
    if args.dry_run:
        print(format_estimate(estimate(config, keys)))
        if (run_dir / "results.jsonl").exists():
            done = len(Ledger.open(run_dir).records)
            print(f"{run_dir}: {done} of {len(keys)} episodes already finished")
        return 0
    try:
        check_run_dir(run_dir, config, keys, config.document())
    except RunDirMismatch as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    try:
        sweep = LocalSweep(config, keys, run_dir)
    except LedgerError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if config.executor.kind in ("ray", "processes"):
        from vabench.sweep.process_executor import run_processes
        from vabench.sweep.ray_executor import run_ray

        run_cells = run_ray if config.executor.kind == "ray" else run_processes
        try:
            records = run_cells(config, keys, run_dir)
        except LedgerError as err:  # e.g. a cell retried by Ray wrote a second record
            print(f"error: {err}", file=sys.stderr)
            return 2
        except SweepStopped as err:
            print(f"stopped: {err}", file=sys.stderr)
            return 2
    else:
        display = Display(len(keys), live=False if args.plain else None)
        sweep.on_change = display.update
        progress = asyncio.run(sweep.run())
        display.close(progress)
        if sweep.stopped is not None:
            print(f"stopped: {sweep.stopped}", file=sys.stderr)
            return 2
        records = sweep.ledger.records
    missing = [k.as_id() for k in keys if ledger_key(k) not in records]
    unscored = [r for r in records.values() if r["status"] not in ("success", "failure")]
    for r in unscored:
        print(f"unscored: {r['episode_dir']}: {r['status']} ({r['stop_reason']}): {r['error']}")
    if missing:
        print(f"{len(missing)} planned episodes have no record: {missing[:5]} ...")
    if not args.no_report:
        from vabench.report import ReportError, make_report

        try:
            print(f"report: {make_report(run_dir)}")
        except ReportError as err:  # e.g. every episode unscored: nothing to tabulate
            print(f"no report: {err}", file=sys.stderr)
    return 0 if not unscored and not missing else 1


if __name__ == "__main__":
    sys.exit(main())
