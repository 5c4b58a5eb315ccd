"""`python -m vabench.report RUN_DIR`: write RUN_DIR/report/ and print a short summary."""

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
        description=f"Tables, figures and {REPORT_HTML} from a sweep's {RESULTS}.",
    )
    parser.add_argument("run_dir", type=Path, help="the sweep's run directory")
    args = parser.parse_args(argv)
    try:
        out = generate(args.run_dir)
    except ReportError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(out.files)} files to {out.directory} (open {REPORT_HTML})")
    for line in out.summary:
        print(f"  {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
