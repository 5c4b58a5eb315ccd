"""`python -m vabench.report RUN_DIR`: write RUN_DIR/report/ and print a short summary.

`python -m vabench.report RUN_DIR RUN_DIR ... --out BOARD` (or a directory of run directories)
merges the models of several sweeps into one report in BOARD (`leaderboard`), after checking
that their scores are comparable.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vabench.report.build import generate
from vabench.run_layout import REPORT_HTML, RESULTS
from vabench.run_records import ReportError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vabench.report",
        description=f"Tables, figures and {REPORT_HTML} from a sweep's {RESULTS}, or a "
        "leaderboard over several sweeps.",
    )
    parser.add_argument(
        "run_dir",
        type=Path,
        nargs="+",
        help="the sweep's run directory; several, or a directory of run directories: a "
        "leaderboard (with --out)",
    )
    parser.add_argument(
        "--out", type=Path, help="where a leaderboard's report goes (required for one)"
    )
    parser.add_argument(
        "--allow-mismatch",
        action="store_true",
        help="merge sweeps whose settings differ, marking every affected row",
    )
    args = parser.parse_args(argv)
    (first,) = args.run_dir[:1]
    holds_runs = first.is_dir() and any((p / RESULTS).is_file() for p in first.iterdir())
    one = len(args.run_dir) == 1 and ((first / RESULTS).is_file() or not holds_runs)
    try:
        if one and args.out is None:
            out = generate(first)  # a missing results file is its own one-line error
        else:
            if args.out is None:
                raise ReportError(
                    "several run directories make a leaderboard: name where it goes with --out DIR"
                )
            from vabench.report.leaderboard import generate_board

            out = generate_board(args.run_dir, args.out, args.allow_mismatch)
    except ReportError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(out.files)} files to {out.directory} (open {REPORT_HTML})")
    for line in out.summary:
        print(f"  {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
