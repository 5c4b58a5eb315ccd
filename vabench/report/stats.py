"""The paper's base aggregation, as pure functions over scored records.

Definitions (paper, "Base evaluation protocol"):

- Per-task success of model m, track t, run r, task τ: successes / scored episodes (20 seeds in
  the paper; infrastructure failures are re-run and never scored, so the total is whatever was
  scored).
- Run-level macro-average over a subset of families (single-arm, dual-arm, all): the unweighted
  mean of the per-task rates of the families present in that run. A family is dual-arm when its
  task uses more than one arm (`arms[task] > 1`).
- Across runs: mean and SAMPLE standard deviation (n - 1) of the run-level macro-averages; the
  SD of a single run is undefined (None).
- Skipped episodes: an episode the model stopped before taking any step (stop reason
  model_stop, no step used) is a failure here, and is counted apart (`Cell.skipped`) so that
  comparisons between two sides (`active_passive`, `suites`) can leave out a side that
  attempted nothing.
- Subtask progress: a micro-average, checkpoints reached / checkpoints possible over every
  scored episode of a model and track (each episode contributes `progress` of `n_checkpoints`).

Rates are exact `Fraction`s so tests can assert exact answers; only the SD, a square root, is a
float (its exact square is `Spread.variance`).
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import TypeVar

from vabench.agent.records import EpisodeResult, TokenTotals
from vabench.run_records import Record, ReportError

SUBSETS = ("single", "dual", "all")
SUBSET_TITLES = {"single": "Single-arm", "dual": "Dual-arm", "all": "All"}
TOKEN_FIELDS = tuple(TokenTotals.model_fields)
"""The token counts of a record (`EpisodeResult.tokens`), in the order the tables show them."""
K = TypeVar("K")


def is_skipped(result: EpisodeResult) -> bool:
    """A scored episode the model ended before its first step: stopped at once, nothing tried."""
    return (
        result.scored
        and not result.success
        and result.stop_reason == "model_stop"
        and result.steps_used == 0
    )


def skipped_side(
    first: bool, second: bool, sides: tuple[str, str] = ("active", "passive")
) -> str | None:
    """Which of the two `sides` had every episode skipped (`first`, `second`), "both" or
    None."""
    if first and second:
        return "both"
    return sides[0] if first else (sides[1] if second else None)


@dataclass(frozen=True)
class Cell:
    """Success count of one (model, track, task, run); `skipped` of the `total` episodes were
    stopped before any step (`is_skipped`)."""

    model: str
    track: str
    task: str
    run: int
    successes: int
    total: int
    skipped: int = 0

    @property
    def rate(self) -> Fraction:
        return Fraction(self.successes, self.total)

    @property
    def all_skipped(self) -> bool:
        return self.skipped == self.total


@dataclass(frozen=True)
class Macro:
    """Run-level macro-average over one subset; `rate` is None when no family of it ran."""

    model: str
    track: str
    run: int
    subset: str
    families: tuple[str, ...]
    rate: Fraction | None


@dataclass(frozen=True)
class Spread:
    """Mean and sample SD of run-level values (`sd` and `variance` None for one value)."""

    values: tuple[Fraction, ...]
    mean: Fraction
    variance: Fraction | None
    sd: float | None

    @property
    def n(self) -> int:
        return len(self.values)


@dataclass(frozen=True)
class Checkpoints:
    model: str
    track: str
    subset: str
    reached: int
    possible: int

    @property
    def rate(self) -> Fraction | None:
        return Fraction(self.reached, self.possible) if self.possible else None


@dataclass(frozen=True)
class Usage:
    """Per model and track, over scored episodes: sums, and shares as ratios of sums."""

    model: str
    track: str
    episodes: int
    steps_used: int
    robot_actions: int
    camera_actions: int
    invalid_actions: int
    model_calls: int
    invalid_outputs: int
    tokens: Mapping[str, int]
    cost_usd: float

    @property
    def mean_steps(self) -> float:
        return self.steps_used / self.episodes

    @property
    def camera_share(self) -> float | None:
        """Camera actions / steps used."""
        return self.camera_actions / self.steps_used if self.steps_used else None

    @property
    def invalid_output_share(self) -> float | None:
        """Replies rejected by the protocol / model calls."""
        return self.invalid_outputs / self.model_calls if self.model_calls else None

    @property
    def invalid_action_share(self) -> float | None:
        """Robot actions the simulator refused or could not plan / robot actions."""
        return self.invalid_actions / self.robot_actions if self.robot_actions else None

    @property
    def total_tokens(self) -> int:
        return sum(self.tokens.values())


def subset_of(task: str, arms: Mapping[str, int]) -> str:
    """ "single" or "dual" from the number of arms the task uses."""
    if task not in arms:
        raise ReportError(f"field 'task': unknown task {task!r}; known tasks: {sorted(arms)}")
    return "dual" if arms[task] > 1 else "single"


def tally(records: Iterable[Record], key: Callable[[Record], K]) -> dict[K, tuple[int, int, int]]:
    """Successes, scored episodes and skipped episodes (`is_skipped`) per key, over the scored
    records, sorted by key."""
    counts: dict[K, list[int]] = defaultdict(lambda: [0, 0, 0])
    for rec in records:
        r = rec.result
        if r.scored:
            c = counts[key(rec)]
            c[0] += int(r.success)
            c[1] += 1
            c[2] += int(is_skipped(r))
    return {k: (s, t, n) for k, (s, t, n) in sorted(counts.items())}


def task_cells(records: Iterable[Record]) -> list[Cell]:
    """Successes and scored totals per (model, track, task, run), sorted by those keys."""
    counts = tally(
        records, lambda rec: (rec.result.model, rec.track, rec.result.task, rec.result.run)
    )
    return [Cell(*k, successes=s, total=t, skipped=n) for k, (s, t, n) in counts.items()]


def macro_averages(cells: Sequence[Cell], arms: Mapping[str, int]) -> list[Macro]:
    """Run-level macro-averages over the single-arm, dual-arm and all families present."""
    by_run: dict[tuple[str, str, int], list[Cell]] = defaultdict(list)
    for c in cells:
        by_run[(c.model, c.track, c.run)].append(c)
    out = []
    for (model, track, run), group in sorted(by_run.items()):
        for subset in SUBSETS:
            chosen = [c for c in group if subset == "all" or subset_of(c.task, arms) == subset]
            rate = average([c.rate for c in chosen]) if chosen else None
            families = tuple(sorted(c.task for c in chosen))
            out.append(Macro(model, track, run, subset, families, rate))
    return out


def average(values: Sequence[Fraction]) -> Fraction:
    """The unweighted mean of at least one value."""
    return sum(values, Fraction(0)) / len(values)


def mean_sd(values: Sequence[Fraction]) -> Spread:
    """Mean and sample standard deviation (divisor n - 1)."""
    if not values:
        raise ValueError("mean_sd of no values")
    vals = tuple(Fraction(v) for v in values)
    mean = average(vals)
    if len(vals) < 2:
        return Spread(vals, mean, None, None)
    variance = sum(((v - mean) ** 2 for v in vals), Fraction(0)) / (len(vals) - 1)
    return Spread(vals, mean, variance, math.sqrt(variance))


def mean_sd_or_none(values: Sequence[Fraction]) -> Spread | None:
    """`mean_sd`, or None for no values."""
    return mean_sd(values) if values else None


def macro_spread(macros: Sequence[Macro]) -> dict[tuple[str, str, str], Spread]:
    """(model, track, subset) -> mean and sample SD over the runs where the subset ran."""
    values: dict[tuple[str, str, str], list[Fraction]] = defaultdict(list)
    for m in sorted(macros, key=lambda m: (m.model, m.track, m.subset, m.run)):
        if m.rate is not None:
            values[(m.model, m.track, m.subset)].append(m.rate)
    return {k: mean_sd(v) for k, v in sorted(values.items())}


def task_spread(cells: Sequence[Cell]) -> dict[tuple[str, str, str], Spread]:
    """(model, track, task) -> mean and sample SD of the per-run success rates."""
    values: dict[tuple[str, str, str], list[Fraction]] = defaultdict(list)
    for c in sorted(cells, key=lambda c: (c.model, c.track, c.task, c.run)):
        values[(c.model, c.track, c.task)].append(c.rate)
    return {k: mean_sd(v) for k, v in sorted(values.items())}


def checkpoint_micro(records: Iterable[Record], arms: Mapping[str, int]) -> list[Checkpoints]:
    """Checkpoints reached / possible per (model, track), for single, dual and all families."""
    sums: dict[tuple[str, str, str], list[int]] = defaultdict(lambda: [0, 0])
    for rec in records:
        r = rec.result
        if not r.scored:
            continue
        for subset in (subset_of(r.task, arms), "all"):
            s = sums[(r.model, rec.track, subset)]
            s[0] += r.progress
            s[1] += r.n_checkpoints
    order = {s: i for i, s in enumerate(SUBSETS)}
    keys = sorted(sums, key=lambda k: (k[0], k[1], order[k[2]]))
    return [Checkpoints(*k, reached=sums[k][0], possible=sums[k][1]) for k in keys]


def usage(records: Iterable[Record]) -> list[Usage]:
    """Steps, action shares, tokens and cost per (model, track) over scored episodes."""
    groups: dict[tuple[str, str], list[Record]] = defaultdict(list)
    for rec in records:
        if rec.result.scored:
            groups[(rec.result.model, rec.track)].append(rec)
    out = []
    for (model, track), recs in sorted(groups.items()):
        rs = [r.result for r in recs]
        tokens = {name: sum(getattr(r.tokens, name) for r in rs) for name in TOKEN_FIELDS}
        out.append(
            Usage(
                model=model,
                track=track,
                episodes=len(rs),
                steps_used=sum(r.steps_used for r in rs),
                robot_actions=sum(r.robot_actions for r in rs),
                camera_actions=sum(r.camera_actions for r in rs),
                invalid_actions=sum(r.invalid_actions for r in rs),
                model_calls=sum(r.model_calls for r in rs),
                invalid_outputs=sum(r.invalid_outputs for r in rs),
                tokens=tokens,
                cost_usd=math.fsum(r.cost_usd for r in rs),
            )
        )
    return out


def unscored_counts(records: Iterable[Record]) -> dict[tuple[str, str, str], tuple[int, float]]:
    """(model, track, status) -> (number of unscored records, their cost in USD)."""
    sums: dict[tuple[str, str, str], list[float]] = defaultdict(lambda: [0, 0.0])
    for rec in records:
        r = rec.result
        if r.scored:
            continue
        s = sums[(r.model, rec.track, r.status)]
        s[0] += 1
        s[1] += r.cost_usd
    return {k: (int(v[0]), v[1]) for k, v in sorted(sums.items())}


def unresolved(scored: Iterable[Record], unscored: Iterable[Record]) -> list[tuple]:
    """Episodes (model, track, task, seed, run) with an unscored record and no scored one."""
    done = {r.key for r in scored}
    return sorted({r.key for r in unscored} - done)


def coverage_notes(cells: Sequence[Cell], expected: Sequence[str]) -> list[str]:
    """Where a run's families differ from `expected`: one line per distinct difference, listing
    the (model, track) runs that share it. Runs with no expected family at all (tracks of
    another suite, which have their own sections) are not notes."""
    present: dict[tuple[str, str, int], set[str]] = defaultdict(set)
    for c in cells:
        present[(c.model, c.track, c.run)].add(c.task)
    groups: dict[tuple[tuple[str, ...], tuple[str, ...]], dict[tuple[str, str], list[int]]] = {}
    for (model, track, run), tasks in sorted(present.items()):
        if not tasks & set(expected):
            continue  # a track of another suite (transfer, long horizon): not a partial base run
        missing = tuple(t for t in expected if t not in tasks)
        extra = tuple(sorted(tasks - set(expected)))
        if missing or extra:
            groups.setdefault((missing, extra), {}).setdefault((model, track), []).append(run)
    notes = []
    for (missing, extra), who in groups.items():
        parts = []
        if missing:
            parts.append(f"lacks {len(missing)} of {len(expected)} base families {list(missing)}")
        if extra:
            parts.append(f"includes non-base tasks {list(extra)}")
        runs = "; ".join(f"{m} / {t} run {','.join(map(str, rs))}" for (m, t), rs in who.items())
        notes.append(f"{' and '.join(parts)}: {runs}")
    return notes
