"""The paper's three headline views of a run, as pure functions: overall success per condition,
the task-by-model matrix, and the capability profile over the nine diagnostics.

- Conditions: a (model, track) whose track ran base families under the active protocol (the
  paper's primary conditions; other protocols and suites have their own sections). Ordered as
  the paper orders its columns: by descending all-families mean, then by name.
- Overall success: the paper's eq. base-success as `stats` computes it: per run, the
  unweighted mean of the per-task rates over the single-arm, dual-arm and all families; across
  runs, the mean and the sample SD of those run-level macro-averages.
- Task matrix: per task (the paper's row order, `published.PAPER_TASK_ORDER`, then any other
  task by name) and condition, the mean and sample SD across runs of the per-task rate.
- Capability profile: per annotated condition, each criterion's share of positive majority
  labels among its applicable episodes, exactly the diagnostics' "Per condition" table
  (`diagnostics.aggregate.criterion_scores`): ED, OC and PF count only episodes whose majority
  error gate is 1 (error-free episodes are NA), AE only those whose ambiguity gate is 1; a
  criterion with no applicable episode is NA, drawn as a gap, never as 0. The annotated runs
  are named: the paper annotates one run per condition; annotations spread over several runs
  are pooled and the runs listed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from vabench.report.published import PAPER_TASK_ORDER
from vabench.report.stats import Cell, Spread
from vabench.run_records import Record

if TYPE_CHECKING:
    from vabench.diagnostics.sections import DiagnosticsData

Condition = tuple[str, str]
"""(model, track)."""


def primary_conditions(records: Sequence[Record], base: Sequence[str]) -> list[Condition]:
    """Every (model, track) with a scored base-family episode under the active protocol."""
    families = set(base)
    return sorted(
        {
            (r.result.model, r.track)
            for r in records
            if r.result.scored and r.result.protocol == "active" and r.result.task in families
        }
    )


def ranked(
    conditions: Sequence[Condition], spreads: Mapping[tuple[str, str, str], Spread]
) -> list[Condition]:
    """Best all-families mean first (the paper's column order), ties by name."""

    def key(c: Condition) -> tuple[float, Condition]:
        s = spreads.get((*c, "all"))
        return (-float(s.mean) if s is not None else 1.0, c)

    return sorted(conditions, key=key)


def label(condition: Condition, conditions: Sequence[Condition]) -> str:
    """The model's name, with the track when the model has more than one condition."""
    model, track = condition
    tracks = sum(1 for m, _ in conditions if m == model)
    return model if tracks == 1 else f"{model} / {track}"


def task_order(tasks: set[str] | Sequence[str]) -> list[str]:
    """The paper's row order, then tasks it does not have by name."""
    rank = {t: i for i, t in enumerate(PAPER_TASK_ORDER)}
    return sorted(set(tasks), key=lambda t: (rank.get(t, len(rank)), t))


@dataclass(frozen=True)
class Bars:
    """One condition's bars: subset -> (mean %, SD %; None with one run); `reference`: a
    published row, drawn grey; `mark`: a flag after its label (a comparability mismatch)."""

    label: str
    values: Mapping[str, tuple[float, float | None]]
    reference: bool = False
    mark: str = ""


@dataclass(frozen=True)
class Matrix:
    tasks: tuple[str, ...]
    conditions: tuple[Condition, ...]
    cells: Mapping[tuple[str, Condition], Spread]
    """(task, condition) -> mean and sample SD across runs of the per-task rate."""


def task_matrix(
    cells: Sequence[Cell],
    task_spreads: Mapping[tuple[str, str, str], Spread],
    conditions: Sequence[Condition],
) -> Matrix:
    chosen = set(conditions)
    tasks = task_order({c.task for c in cells if (c.model, c.track) in chosen})
    by = {
        (task, cond): s
        for (model, track, task), s in task_spreads.items()
        if (cond := (model, track)) in chosen
    }
    return Matrix(tuple(tasks), tuple(conditions), by)


CRITERIA = ("TL", "AE", "SR", "MS", "MP", "FG", "ED", "OC", "PF")
"""The radar's axes, clockwise from the top: the three modules in the paper's order."""


@dataclass(frozen=True)
class Profile:
    """One condition's capability profile: each criterion's % (None: NA) and its n."""

    model: str
    track: str
    runs: tuple[int, ...]
    """The runs the annotated episodes belong to (the paper: one)."""
    episodes: int
    values: Mapping[str, float | None]
    n: Mapping[str, int]

    @property
    def runs_text(self) -> str:
        if not self.runs:
            return "—"
        word = "run" if len(self.runs) == 1 else "runs"
        pooled = "" if len(self.runs) == 1 else " pooled"
        return f"{word} {','.join(map(str, self.runs))}{pooled}"


def profiles(data: DiagnosticsData | None) -> list[Profile]:
    """The capability profile of every annotated condition (see the module docstring)."""
    if data is None:
        return []
    from vabench.diagnostics import aggregate as agg

    scores = agg.criterion_scores(data.collected, data.index, agg.condition_of)
    runs: dict[tuple[str, ...], set[int]] = {}
    episodes: dict[tuple[str, ...], int] = {}
    for episode in data.collected.gates:
        ref = data.index.episodes[episode]
        group = agg.condition_of(ref)
        runs.setdefault(group, set()).add(ref.result.run)
        episodes[group] = episodes.get(group, 0) + 1
    out = []
    for group, by in scores.items():
        model, track = group[0], group[1]
        out.append(
            Profile(
                model,
                track,
                tuple(sorted(runs.get(group, ()))),
                episodes.get(group, 0),
                {c: None if (v := by[c].value) is None else 100 * v for c in CRITERIA},
                {c: by[c].n for c in CRITERIA},
            )
        )
    return out
