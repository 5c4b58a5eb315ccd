"""Demonstration summaries in the report: the summary-source comparison (paper,
tab:summary-source-ablation and tab:summary-cross-eval) and the learning stage's sessions, as
pure functions over condition cells (`conditions`) and RUN_DIR/summaries/.

- Summary source: for one model, one protocol and one suite (base, transfer, ...: compared
  apart, as each suite has its own section) run under two summary modes or more, the *matched
  tasks* are those with scored records under every mode, and the *matched runs* the run
  numbers present under every mode. Per mode: run-level macro-averages (single-arm, dual-arm,
  all) over the matched tasks, mean and sample SD across that mode's runs; "mode − own" is the
  difference of the means.
- Cross-model: a model's rate under a mode is pooled success (successes / episodes) over its
  matched tasks and matched runs; Δ = shared − own. The avg row averages the models' rates
  unweighted; its Δ leaves out the summary author (whose own summary is the shared one).
- Learning stage: one row per session file RUN_DIR/summaries/<model>/<family>.json
  (`RunDir.summary_files`).
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

from vabench.report.conditions import OWN, CondCell
from vabench.report.stats import SUBSETS, Spread, average, mean_sd_or_none, subset_of
from vabench.run_layout import RunDir
from vabench.run_records import Record, ReportError, validation_problems


def mode_rank(mode: str) -> tuple[int, str]:
    """own first, then shared:<model> by name, then none (and anything else) last."""
    if mode == OWN:
        return (0, mode)
    return (1, mode) if mode.startswith("shared:") else (2, mode)


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


def _mean(values: Sequence[Fraction]) -> Fraction | None:
    return average(values) if values else None


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
                        per_run.append(average(rates))
                macros[(mode, subset)] = mean_sd_or_none(per_run)
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


def learning_rows(run: RunDir) -> list[LearningRow]:
    """One row per learning session (`RunDir.summary_files`; none when the sweep learned
    nothing)."""
    paths = run.summary_files()
    if not paths:
        return []
    from pydantic import ValidationError

    from vabench.agent.learning import read_result  # the agent stack: only when needed

    rows = []
    for path in paths:
        try:
            r = read_result(path)
        except json.JSONDecodeError as exc:
            raise ReportError(f"{path}: not valid JSON ({exc.msg})") from None
        except ValidationError as exc:
            raise ReportError(f"{path}: {validation_problems(exc)}") from None
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
