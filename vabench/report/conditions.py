"""What the tracks beyond the base evaluation group records by: a *condition*, and the task
metadata the records do not carry.

Records are grouped by what an episode ran under, a condition = (model, camera protocol,
summary mode), not by track name: the sweep names tracks freely (`active_none`, `transfer`),
while the record itself says its protocol and `summary_mode` ("own" | "none" |
"shared:<model>"). Which suite a task belongs to and which base family a held-out variant comes
from are not in the records; they come from a `TaskMeta` (the registry's, or a hand-made one).
The statistics over conditions: `summaries` (summary source, learning stage) and `suites`
(controlled transfer, long horizon).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from vabench.report.stats import Cell, tally
from vabench.run_records import Record

OWN = "own"
"""The summary mode of a model reading its own demonstration summary."""


@dataclass(frozen=True)
class TaskMeta:
    """What the records do not say about a task."""

    suite: Mapping[str, str]
    """task -> "base" | "transfer" | "long_horizon" | "dev"; a task not listed is in no suite."""
    base_family: Mapping[str, str]
    """held-out task -> the base family it is held out from."""


@dataclass(frozen=True, kw_only=True)
class CondCell(Cell):
    """Success count of one (model, protocol, summary mode, task, run): the `Cell` of the track
    counted for it (`condition_cells`)."""

    protocol: str
    mode: str


def condition_cells(records: Iterable[Record]) -> tuple[list[CondCell], list[str]]:
    """Cells per condition, and notes. When two tracks ran the same condition and task (say
    `active` and a copy of it under another name), only the first track by name is counted: the
    same episodes would otherwise count twice."""
    counts: dict[tuple[str, str, str, str, int, str], tuple[int, int, int]] = tally(
        records,
        lambda rec: (
            rec.result.model,
            rec.result.protocol,
            rec.result.summary_mode,
            rec.result.task,
            rec.result.run,
            rec.track,
        ),
    )
    tracks: dict[tuple[str, str, str, str], set[str]] = defaultdict(set)
    for model, protocol, mode, task, _, track in counts:
        tracks[(model, protocol, mode, task)].add(track)
    cells, notes = [], []
    for (model, protocol, mode, task, run, track), (s, t, n) in counts.items():
        if track == min(tracks[(model, protocol, mode, task)]):
            cells.append(CondCell(model, track, task, run, s, t, n, protocol=protocol, mode=mode))
    for (model, protocol, mode, task), names in sorted(tracks.items()):
        if len(names) > 1:
            first, *rest = sorted(names)
            notes.append(
                f"{model} / {protocol} / summaries {mode} / {task}: run by tracks "
                f"{[first, *rest]} alike; only {first!r} is counted"
            )
    return cells, notes
