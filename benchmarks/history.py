"""The dated history of benchmark figures, from benchmarks/results/*.json.

    python benchmarks/history.py [FIGURE-SUBSTRING] [--verbose]
    python benchmarks/history.py --list

Prints every record whose figure (or topic) contains the substring, case-insensitively, as a
table ordered by date; `--verbose` adds each record's command and note. `--list` names the
figures, each with its topic and how many records it has. docs/PERFORMANCE.md shows the
newest figure of each thing; the records behind it are written by `results_log.append`.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

from results_log import RESULTS_DIR, read_topic


def load(results_dir: Path = RESULTS_DIR) -> list[dict]:
    """Every record of every topic, each with its `topic` added."""
    records = []
    for path in sorted(Path(results_dir).glob("*.json")):
        records.extend({**r, "topic": path.stem} for r in read_topic(path))
    return records


def matching(records: list[dict], substring: str = "") -> list[dict]:
    """The records whose figure or topic contains `substring`, ordered by date."""
    needle = substring.lower()
    found = [r for r in records if needle in r["figure"].lower() or needle in r["topic"]]
    return sorted(found, key=lambda r: (r["date"], r["figure"]))


def figure_names(records: list[dict]) -> list[tuple[str, str, int]]:
    """(topic, figure, number of records), sorted."""
    counts = Counter((r["topic"], r["figure"]) for r in records)
    return [(topic, figure, n) for (topic, figure), n in sorted(counts.items())]


def _value(record: dict) -> str:
    return f"{record['value']:,.6g} {record['unit']}"


def _ratio(record: dict) -> str:
    if record.get("ratio") is None:
        return record.get("baseline") or ""
    return f"{record['ratio']:.3g}x {record['baseline']}"


def table(records: list[dict], verbose: bool = False) -> str:
    """The records as an aligned text table, one row each."""
    head = ("date", "figure", "value", "vs baseline", "machine", "commit")
    rows = [
        (r["date"], r["figure"], _value(r), _ratio(r), r["machine"], r.get("commit") or "")
        for r in records
    ]
    widths = [max(len(str(row[i])) for row in [head, *rows]) for i in range(len(head))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(head, widths, strict=True)).rstrip()]
    for row, r in zip(rows, records, strict=True):
        lines.append("  ".join(str(c).ljust(w) for c, w in zip(row, widths, strict=True)).rstrip())
        if verbose:
            lines.append(f"    $ {r['command']}")
            lines.append(f"    {r['note']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("figure", nargs="?", default="", help="a part of the figure's name or topic")
    p.add_argument("--list", action="store_true", help="list the figures instead")
    p.add_argument("--verbose", "-v", action="store_true", help="add commands and notes")
    p.add_argument("--dir", type=Path, default=RESULTS_DIR, help="the results folder")
    args = p.parse_args(argv)
    records = load(args.dir)
    if args.list:
        names = [n for n in figure_names(records) if args.figure.lower() in n[1].lower() + n[0]]
        for topic, figure, n in names:
            print(f"{topic:<16} {figure}  ({n})")
        return 0
    found = matching(records, args.figure)
    if not found:
        print(f"no figure matches {args.figure!r}; `--list` names them", file=sys.stderr)
        return 1
    print(table(found, args.verbose))
    return 0


if __name__ == "__main__":
    sys.exit(main())
