"""Statistics of the tracks beyond the base evaluation, as pure functions over scored records.

Records are grouped by what an episode ran under, a *condition* = (model, camera protocol,
summary mode), not by track name: the sweep names tracks freely (`active_none`, `transfer`),
while the record itself says its protocol and `summary_mode` ("own" | "none" |
"shared:<model>"). Which suite a task belongs to and which base family a held-out variant comes
from are not in the records; they come from a `TaskMeta` (the registry's, or a hand-made one).

- Summary source (paper, tab:summary-source-ablation and tab:summary-cross-eval): for one model,
  one protocol and one suite (base, transfer, ...: compared apart, as each suite has its own
  section) run under two summary modes or more, the *matched tasks* are those with
  scored records under every mode, and the *matched runs* the run numbers present under every
  mode. Per mode: run-level macro-averages (single-arm, dual-arm, all) over the matched tasks,
  mean and sample SD across that mode's runs; "mode − own" is the difference of the means.
  Cross-model: a model's rate under a mode is pooled success (successes / episodes) over its
  matched tasks and matched runs; Δ = shared − own. The avg row averages the models' rates
  unweighted; its Δ leaves out the summary author (whose own summary is the shared one).
- Controlled transfer (tab:generalization-summary, tab:single-arm-generalization): a held-out
  task (suite "transfer") is paired with its base family under the same protocol and the same
  summary mode (falling back to "own"). Per run: the macro-average over the families with both
  sides scored in that run, leaving out a pair whose episodes on one side were all skipped
  (the model stopped before its first step: nothing was attempted, so Δ would measure that,
  not the transfer; such a family is listed with its counts and no Δ); across runs: mean and
  sample SD of the base, held-out and Δ = held-out − base macro-averages. Per family: counts
  pooled over those runs.
- Long-horizon composition: per (model, track, task) of suite "long_horizon" and run, objects
  placed = the sum of `progress` (k checkpoints = k objects) out of the sum of
  `n_checkpoints`, and strict success = successes / episodes.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

from vabench.report.load import Record, ReportError
from vabench.report.stats import SUBSETS, Spread, is_skipped, mean_sd, skipped_side, subset_of

OWN = "own"


@dataclass(frozen=True)
class TaskMeta:
    """What the records do not say about a task."""

    suite: Mapping[str, str]
    """task -> "base" | "transfer" | "long_horizon" | "dev"; a task not listed is in no suite."""
    base_family: Mapping[str, str]
    """held-out task -> the base family it is held out from."""


@dataclass(frozen=True)
class CondCell:
    """Success count of one (model, protocol, summary mode, task, run)."""

    model: str
    protocol: str
    mode: str
    task: str
    run: int
    successes: int
    total: int
    track: str
    skipped: int = 0
    """Episodes stopped before their first step (`stats.is_skipped`)."""

    @property
    def rate(self) -> Fraction:
        return Fraction(self.successes, self.total)

    @property
    def all_skipped(self) -> bool:
        return self.skipped == self.total


def mode_rank(mode: str) -> tuple[int, str]:
    """own first, then shared:<model> by name, then none (and anything else) last."""
    if mode == OWN:
        return (0, mode)
    return (1, mode) if mode.startswith("shared:") else (2, mode)


def condition_cells(records: Iterable[Record]) -> tuple[list[CondCell], list[str]]:
    """Cells per condition, and notes. When two tracks ran the same condition and task (say
    `active` and a copy of it under another name), only the first track by name is counted: the
    same episodes would otherwise count twice."""
    counts: dict[tuple[str, str, str, str, int, str], list[int]] = defaultdict(lambda: [0, 0, 0])
    for rec in records:
        r = rec.result
        if r.scored:
            c = counts[(r.model, r.protocol, r.summary_mode, r.task, r.run, rec.track)]
            c[0] += int(r.success)
            c[1] += 1
            c[2] += int(is_skipped(r))
    tracks: dict[tuple[str, str, str, str], set[str]] = defaultdict(set)
    for model, protocol, mode, task, _, track in counts:
        tracks[(model, protocol, mode, task)].add(track)
    cells, notes = [], []
    for (model, protocol, mode, task, run, track), (s, t, n) in sorted(counts.items()):
        if track == min(tracks[(model, protocol, mode, task)]):
            cells.append(CondCell(model, protocol, mode, task, run, s, t, track, n))
    for (model, protocol, mode, task), names in sorted(tracks.items()):
        if len(names) > 1:
            first, *rest = sorted(names)
            notes.append(
                f"{model} / {protocol} / summaries {mode} / {task}: run by tracks "
                f"{[first, *rest]} alike; only {first!r} is counted"
            )
    return cells, notes


def failed_summary_notes(records: Iterable[Record]) -> list[str]:
    """Scored episodes whose summary could not be learned (they ran without one), per model
    and track: they stay under their track's mode, as the sweep ran them."""
    counts: dict[tuple[str, str, str], int] = defaultdict(int)
    for rec in records:
        r = rec.result
        if r.scored and r.summary_status == "failed":
            source = r.model if r.summary_mode == OWN else r.summary_mode.removeprefix("shared:")
            counts[(r.model, rec.track, source)] += 1
    return [
        f"{model} / {track}: {n} episode(s) ran without a summary ({source}'s learning failed)"
        for (model, track, source), n in sorted(counts.items())
    ]


def _rate(pairs: Iterable[tuple[int, int]]) -> Fraction | None:
    s = t = 0
    for a, b in pairs:
        s, t = s + a, t + b
    return Fraction(s, t) if t else None


def _avg(values: Sequence[Fraction]) -> Fraction:
    """The mean of at least one value."""
    return sum(values, Fraction(0)) / len(values)


def _mean(values: Sequence[Fraction]) -> Fraction | None:
    return _avg(values) if values else None


def _spread(values: Sequence[Fraction]) -> Spread | None:
    return mean_sd(values) if values else None


# -- summary source ------------------------------------------------------------------------------


@dataclass(frozen=True)
class SummaryComparison:
    """One model and protocol under several summary modes, over its matched tasks."""

    model: str
    protocol: str
    suite: str
    modes: tuple[str, ...]
    tasks: tuple[str, ...]
    """Matched tasks: scored under every mode."""
    left_out: tuple[str, ...]
    """Tasks scored under some of the modes only."""
    runs: tuple[int, ...]
    """Matched runs: present under every mode (the pooled rates use these)."""
    mode_runs: Mapping[str, tuple[int, ...]]
    macros: Mapping[tuple[str, str], Spread | None]
    """(mode, subset) -> run-level macro-averages over the matched tasks, across the mode's runs."""
    counts: Mapping[tuple[str, str], tuple[int, int]]
    """(mode, task) -> successes and episodes over the matched runs."""

    def pooled(self, mode: str, task: str | None = None) -> Fraction | None:
        """Pooled success over the matched runs, of one matched task or of all of them."""
        tasks = self.tasks if task is None else (task,)
        return _rate(self.counts[(mode, t)] for t in tasks if (mode, t) in self.counts)

    def delta(self, mode: str, subset: str) -> Fraction | None:
        """Mean macro-average under `mode` minus under own (None without own or data)."""
        a, b = self.macros.get((mode, subset)), self.macros.get((OWN, subset))
        return None if a is None or b is None else a.mean - b.mean


def summary_comparisons(
    cells: Sequence[CondCell], arms: Mapping[str, int], suites: Mapping[str, str] | None = None
) -> tuple[list[SummaryComparison], list[str]]:
    """One comparison per (model, protocol, suite) scored under >= 2 summary modes on >= 1
    common task; notes for the ones left out for want of a common task. A task missing from
    `suites` (or every task, without it) counts as "base"."""
    groups: dict[tuple[str, str, str], list[CondCell]] = defaultdict(list)
    for c in cells:
        groups[(c.model, c.protocol, (suites or {}).get(c.task, "base"))].append(c)
    out, notes = [], []
    for (model, protocol, suite), group in sorted(groups.items(), key=_suite_first):
        modes = tuple(sorted({c.mode for c in group}, key=mode_rank))
        if len(modes) < 2:
            continue
        tasks_of = {m: {c.task for c in group if c.mode == m} for m in modes}
        runs_of = {m: tuple(sorted({c.run for c in group if c.mode == m})) for m in modes}
        matched = set.intersection(*tasks_of.values())
        if not matched:
            notes.append(
                f"{model} / {protocol}{suite_label(suite)}: summary modes {list(modes)} "
                "share no task"
            )
            continue
        runs = tuple(sorted(set.intersection(*(set(r) for r in runs_of.values()))))
        macros: dict[tuple[str, str], Spread | None] = {}
        for mode in modes:
            for subset in SUBSETS:
                per_run = []
                for run in runs_of[mode]:
                    rates = [
                        c.rate
                        for c in group
                        if c.mode == mode
                        and c.run == run
                        and c.task in matched
                        and (subset == "all" or subset_of(c.task, arms) == subset)
                    ]
                    if rates:
                        per_run.append(_avg(rates))
                macros[(mode, subset)] = _spread(per_run)
        counts: dict[tuple[str, str], tuple[int, int]] = {}
        for c in group:
            if c.task in matched and c.run in runs:
                s, t = counts.get((c.mode, c.task), (0, 0))
                counts[(c.mode, c.task)] = (s + c.successes, t + c.total)
        out.append(
            SummaryComparison(
                model=model,
                protocol=protocol,
                suite=suite,
                modes=modes,
                tasks=tuple(sorted(matched)),
                left_out=tuple(sorted(set.union(*tasks_of.values()) - matched)),
                runs=runs,
                mode_runs=runs_of,
                macros=macros,
                counts=counts,
            )
        )
    return out, notes


def suite_label(suite: str) -> str:
    """Appended to a model / protocol label: nothing for the base suite."""
    return "" if suite == "base" else f" ({suite} suite)"


def _suite_first(item: tuple[tuple[str, str, str], Any]) -> tuple:
    model, protocol, suite = item[0]
    return (suite != "base", suite, model, protocol)


@dataclass(frozen=True)
class CrossRow:
    model: str
    own: Fraction | None
    shared: Mapping[str, Fraction | None]
    """source model -> pooled rate with that model's summary."""

    def delta(self, source: str) -> Fraction | None:
        rate = self.shared.get(source)
        return None if rate is None or self.own is None else rate - self.own


@dataclass(frozen=True)
class CrossModel:
    """Rows = evaluated models of one protocol; columns = own and each shared summary source."""

    protocol: str
    suite: str
    sources: tuple[str, ...]
    rows: tuple[CrossRow, ...]

    @property
    def avg_own(self) -> Fraction | None:
        return _mean([r.own for r in self.rows if r.own is not None])

    def avg_rate(self, source: str) -> Fraction | None:
        return _mean([v for r in self.rows if (v := r.shared.get(source)) is not None])

    def avg_delta(self, source: str) -> Fraction | None:
        """Mean Δ over the evaluated models other than the summary's author."""
        return _mean(
            [d for r in self.rows if r.model != source and (d := r.delta(source)) is not None]
        )


def cross_model(comparisons: Sequence[SummaryComparison]) -> list[CrossModel]:
    """Per protocol and suite, the models compared under own and at least one shared summary."""
    groups: dict[tuple[str, str], list[SummaryComparison]] = defaultdict(list)
    for cmp in comparisons:
        if OWN in cmp.modes and any(m.startswith("shared:") for m in cmp.modes):
            groups[(cmp.protocol, cmp.suite)].append(cmp)
    out = []
    for (protocol, suite), cmps in sorted(
        groups.items(), key=lambda kv: (kv[0][1] != "base", kv[0])
    ):
        sources = sorted(
            {m.removeprefix("shared:") for c in cmps for m in c.modes if m.startswith("shared:")}
        )
        rows = tuple(
            CrossRow(
                model=c.model,
                own=c.pooled(OWN),
                shared={s: c.pooled(f"shared:{s}") for s in sources if f"shared:{s}" in c.modes},
            )
            for c in cmps
        )
        out.append(CrossModel(protocol, suite, tuple(sources), rows))
    return out


# -- learning stage ------------------------------------------------------------------------------


@dataclass(frozen=True)
class LearningRow:
    path: Path
    model: str
    family: str
    status: str
    stop_reason: str
    model_calls: int
    frames_inspected: int
    n_frames: int
    learn_refusals: int


def learning_rows(summaries_dir: Path) -> list[LearningRow]:
    """One row per RUN_DIR/summaries/<model>/<family>.json (none when the folder is absent)."""
    if not summaries_dir.is_dir():
        return []
    from pydantic import ValidationError

    from vabench.agent.learning import read_result  # the agent stack: only when needed

    rows = []
    for path in sorted(summaries_dir.rglob("*.json")):
        try:
            r = read_result(path)
        except json.JSONDecodeError as exc:
            raise ReportError(f"{path}: not valid JSON ({exc.msg})") from None
        except ValidationError as exc:
            raise ReportError(f"{path}: {_problems(exc.errors())}") from None
        rows.append(
            LearningRow(
                path=path,
                model=r.model,
                family=r.task,
                status=r.status,
                stop_reason=r.stop_reason,
                model_calls=r.model_calls,
                frames_inspected=len(r.frames_inspected),
                n_frames=r.n_frames,
                learn_refusals=r.learn_refusals,
            )
        )
    return sorted(rows, key=lambda r: (r.model, r.family))


def _problems(errors: Sequence[Mapping[str, Any]]) -> str:
    return "; ".join(f"field '{'.'.join(str(p) for p in e['loc'])}': {e['msg']}" for e in errors)


# -- controlled transfer -------------------------------------------------------------------------


@dataclass(frozen=True)
class TransferFamily:
    heldout: str
    base: str
    base_mode: str
    base_successes: int
    base_total: int
    heldout_successes: int
    heldout_total: int
    base_skipped: int = 0
    heldout_skipped: int = 0

    @property
    def base_rate(self) -> Fraction:
        return Fraction(self.base_successes, self.base_total)

    @property
    def heldout_rate(self) -> Fraction:
        return Fraction(self.heldout_successes, self.heldout_total)

    @property
    def skipped_side(self) -> str | None:
        """ "base", "held-out" or "both" when every episode of that side was skipped (the
        model stopped before its first step): then Δ compares nothing."""
        return skipped_side(
            self.base_skipped == self.base_total,
            self.heldout_skipped == self.heldout_total,
            ("base", "held-out"),
        )

    @property
    def delta(self) -> Fraction | None:
        """Held-out minus base success rate; None when one side was all skipped."""
        return None if self.skipped_side else self.heldout_rate - self.base_rate


@dataclass(frozen=True)
class TransferComparison:
    """One model, protocol and summary mode: held-out variants against their base families."""

    model: str
    protocol: str
    mode: str
    runs: tuple[int, ...]
    families: tuple[TransferFamily, ...]
    base: Spread | None
    heldout: Spread | None
    delta: Spread | None
    """Run-level macro-averages across runs; delta's values are per-run held-out − base."""
    unmatched: tuple[str, ...]
    """Held-out tasks without a scored base-family run under the same protocol and run."""
    skipped: tuple[str, ...] = ()
    """Held-out tasks left out of the macro-averages in some run because every episode of
    one side (base or held-out) was skipped there."""


def transfer_comparisons(cells: Sequence[CondCell], meta: TaskMeta) -> list[TransferComparison]:
    by = {(c.model, c.protocol, c.mode, c.task, c.run): c for c in cells}
    conditions = sorted(
        {(c.model, c.protocol, c.mode) for c in cells if meta.suite.get(c.task) == "transfer"}
    )
    out = []
    for model, protocol, mode in conditions:
        held = [
            c
            for c in cells
            if (c.model, c.protocol, c.mode) == (model, protocol, mode)
            and meta.suite.get(c.task) == "transfer"
        ]
        per_run: dict[int, list[tuple[Fraction, Fraction]]] = defaultdict(list)
        pooled: dict[tuple[str, str, str], list[int]] = {}
        skipped: set[str] = set()
        for h in held:
            base = meta.base_family.get(h.task)
            if base is None:
                raise ReportError(
                    f"task {h.task!r}: suite 'transfer' but field 'base_family' is not set"
                )
            b = next(
                (
                    by[k]
                    for m in dict.fromkeys((mode, OWN))
                    if (k := (model, protocol, m, base, h.run)) in by
                ),
                None,
            )
            if b is None:
                continue
            if b.all_skipped or h.all_skipped:
                skipped.add(h.task)  # nothing attempted on one side: no pair for the macros
            else:
                per_run[h.run].append((b.rate, h.rate))
            p = pooled.setdefault((h.task, base, b.mode), [0, 0, 0, 0, 0, 0])
            p[0], p[1] = p[0] + b.successes, p[1] + b.total
            p[2], p[3] = p[2] + h.successes, p[3] + h.total
            p[4], p[5] = p[4] + b.skipped, p[5] + h.skipped
        runs = tuple(sorted(per_run))
        base_m = [_avg([b for b, _ in per_run[r]]) for r in runs]
        held_m = [_avg([h for _, h in per_run[r]]) for r in runs]
        matched = {task for task, _, _ in pooled}
        out.append(
            TransferComparison(
                model=model,
                protocol=protocol,
                mode=mode,
                runs=runs,
                families=tuple(
                    TransferFamily(t, b, m, *p) for (t, b, m), p in sorted(pooled.items())
                ),
                base=_spread(base_m),
                heldout=_spread(held_m),
                delta=_spread([h - b for b, h in zip(base_m, held_m, strict=True)]),
                unmatched=tuple(sorted({h.task for h in held} - matched)),
                skipped=tuple(sorted(skipped)),
            )
        )
    return out


# -- long-horizon composition --------------------------------------------------------------------


@dataclass(frozen=True)
class LongHorizonRun:
    run: int
    episodes: int
    placed: int
    possible: int
    successes: int

    @property
    def placed_rate(self) -> Fraction:
        return Fraction(self.placed, self.possible) if self.possible else Fraction(0)

    @property
    def success_rate(self) -> Fraction:
        return Fraction(self.successes, self.episodes)


@dataclass(frozen=True)
class LongHorizon:
    model: str
    track: str
    task: str
    runs: tuple[LongHorizonRun, ...]
    placed: Spread
    success: Spread


def long_horizon(records: Iterable[Record], meta: TaskMeta) -> list[LongHorizon]:
    sums: dict[tuple[str, str, str], dict[int, list[int]]] = defaultdict(dict)
    for rec in records:
        r = rec.result
        if not r.scored or meta.suite.get(r.task) != "long_horizon":
            continue
        s = sums[(r.model, rec.track, r.task)].setdefault(r.run, [0, 0, 0, 0])
        s[0] += 1
        s[1] += r.progress
        s[2] += r.n_checkpoints
        s[3] += int(r.success)
    out = []
    for (model, track, task), per_run in sorted(sums.items()):
        runs = tuple(LongHorizonRun(run, *per_run[run]) for run in sorted(per_run))
        out.append(
            LongHorizon(
                model,
                track,
                task,
                runs,
                mean_sd([r.placed_rate for r in runs]),
                mean_sd([r.success_rate for r in runs]),
            )
        )
    return out
