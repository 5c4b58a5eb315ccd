"""`python -m vabench.check CONFIG [--model NAME ...]` (see vabench.check).

Exit code 0 when every model passed, 2 for a bad config or any problem (one line each on
stderr, with its fix). Keys come from the environment, or from a `.env` file beside the
config for the variables the environment does not set, as for the sweep.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from vabench.check import check_sync, problems, report_text
from vabench.config import SweepConfigError, load_config
from vabench.config.keys import key_sources


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m vabench.check",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("config", type=Path)
    p.add_argument(
        "--model",
        action="append",
        metavar="NAME",
        help="check this model of the config only (repeatable; default: every model)",
    )
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    try:
        keys = key_sources(args.config, os.environ)
        config = load_config(args.config, environ=keys.environ, require_keys=False)
    except SweepConfigError as err:
        print(err, file=sys.stderr)
        return 2
    try:
        reports = check_sync(config, keys.environ, args.model)
    except ValueError as err:  # an unknown --model
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(report_text(reports))
    found = problems(reports)
    for line in found:
        print(line.problem_line(), file=sys.stderr)
    if found:
        print(f"{len(found)} problem(s): fix them before a sweep spends", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
