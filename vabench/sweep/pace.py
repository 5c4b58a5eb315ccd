"""The dry run's wall-time estimate: the pace measured by earlier sweeps on this machine.

No model of the machine predicts a sweep's wall time honestly (it depends on the cores, the
GPU, the endpoints' latency, the episodes in flight), so the dry run reads what this machine
did: the most recently written run directory beside the one planned (the same `runs/` parent,
the planned one included) whose ledger holds episodes. Its pace is decisions (steps) per second
of episode time: the steps of its recorded episodes over the union of their
`[started_at, started_at + wall_s]` intervals, so the pauses between a stopped sweep and its
resumption do not count, and neither do learning sessions.

The estimate is the planned episodes not yet recorded, each at its whole step budget (as the
cost estimate assumes), at that pace. It is a guide, not a promise: a pace measured with
another endpoint (the embedded server answers in milliseconds; a real model in seconds), size or
number of episodes in flight does not carry over, and the line says which run it comes from.
With no such run it says so and names the command that measures one.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from vabench.run_layout import RESULTS

NO_PACE = "wall time: no measured pace on this machine yet (run configs/smoke.yaml to measure one)"


@dataclass(frozen=True)
class Pace:
    """What an earlier sweep on this machine measured."""

    run_dir: Path
    episodes: int
    decisions: int
    busy_s: float
    """The union of its episodes' wall-time intervals."""
    finished_at: float

    @property
    def decisions_per_s(self) -> float:
        return self.decisions / self.busy_s if self.busy_s > 0 else 0.0


def measured_pace(runs_parent: Path) -> Pace | None:
    """The pace of the most recently written ledger under `runs_parent` (see the module
    docstring), or None when there is none with a measurable episode."""
    try:
        ledgers = [d / RESULTS for d in runs_parent.iterdir() if (d / RESULTS).is_file()]
    except OSError:  # no runs/ yet, or unreadable: nothing measured
        return None
    for path in sorted(ledgers, key=_mtime, reverse=True):
        pace = _pace_of(path)
        if pace is not None:
            return pace
    return None


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return 0.0


def _pace_of(ledger: Path) -> Pace | None:
    intervals, decisions = [], 0
    try:
        lines = ledger.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return None
    for line in lines:
        try:
            record = json.loads(line)
            start, wall, steps = record["started_at"], record["wall_s"], record["steps_used"]
        except (ValueError, KeyError, TypeError):
            continue  # a cut last line, an older record: not measured
        if isinstance(start, int | float) and isinstance(wall, int | float) and wall > 0:
            intervals.append((float(start), float(start) + float(wall)))
            decisions += int(steps or 0)
    busy = _union_length(intervals)
    if not intervals or decisions == 0 or busy <= 0:
        return None
    return Pace(ledger.parent, len(intervals), decisions, busy, max(e for _, e in intervals))


def _union_length(intervals: Iterable[tuple[float, float]]) -> float:
    total, end = 0.0, float("-inf")
    for a, b in sorted(intervals):
        if b <= end:
            continue
        total += b - max(a, end)
        end = b
    return total


def wall_time_line(pace: Pace | None, decisions_left: int) -> str:
    """The dry run's line (see the module docstring)."""
    if decisions_left == 0:
        return "wall time: nothing left to run"
    if pace is None:
        return NO_PACE
    seconds = decisions_left / pace.decisions_per_s
    when = time.strftime("%Y-%m-%d %H:%M", time.localtime(pace.finished_at))
    return (
        f"wall time: about {_duration(seconds)} if every episode uses its whole budget "
        f"({decisions_left:,} decisions at {pace.decisions_per_s:.2g} a second, the pace of "
        f"{pace.episodes:,} episodes in {pace.run_dir}, the last ended {when}); another "
        "endpoint, size or number in flight changes it"
    )


def _duration(seconds: float) -> str:
    minutes = round(seconds / 60)
    if minutes < 1:
        return f"{max(1, round(seconds))} s"
    if minutes < 60:
        return f"{minutes} min"
    return f"{minutes // 60} h {minutes % 60:02d} min"
