"""Sections on demonstration summaries: summary source and learning stage (statistics:
`summaries`; number formats: `tables`). A builder returns None when the sweep holds no such
data, so a base sweep's report keeps exactly its base sections."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from fractions import Fraction
from typing import Any

from vabench.report.conditions import OWN
from vabench.report.stats import SUBSET_TITLES, SUBSETS, subset_of
from vabench.report.summaries import (
    CrossModel,
    LearningRow,
    SummaryComparison,
    suite_label,
)
from vabench.run_layout import SUMMARIES
from vabench.tables import (
    Csv,
    Section,
    Table,
    mean_sd_text,
    pct,
    runs_label,
    runs_text,
    signed,
)


def mode_label(mode: str) -> str:
    if mode == OWN:
        return "own (model-specific)"
    if mode.startswith("shared:"):
        return f"{mode.removeprefix('shared:')} (shared)"
    return "none (no summary)" if mode == "none" else mode


def summary_section(
    comparisons: Sequence[SummaryComparison],
    cross: Sequence[CrossModel],
    arms: Mapping[str, int],
    notes: list[str],
) -> Section | None:
    """Per model, protocol and suite: the modes' macro-averages; per protocol and suite: the
    cross-model table; per comparison: per-task success by mode."""
    if not comparisons:
        return None
    notes = list(notes)
    tables, abl_rows = _ablation_tables(comparisons, arms, notes)
    cross_tables, cross_rows = _cross_model_tables(cross)
    task_tables, task_rows = _per_task_tables(comparisons)
    tables += cross_tables + task_tables
    return Section(
        "summary_source",
        "Summary source",
        tables,
        [
            Csv(
                "summary_source",
                [
                    "model",
                    "protocol",
                    "suite",
                    "mode",
                    "subset",
                    "tasks",
                    "runs",
                    "mean",
                    "sd",
                    "delta_vs_own",
                ],
                abl_rows,
            ),
            Csv(
                "summary_cross_model",
                [
                    "protocol",
                    "suite",
                    "evaluated_model",
                    "source",
                    "own_rate",
                    "shared_rate",
                    "delta",
                ],
                cross_rows,
            ),
            Csv(
                "summary_per_task",
                ["model", "protocol", "suite", "task", "mode", "successes", "total", "rate"],
                task_rows,
            ),
        ],
        notes,
    )


def _ablation_tables(
    comparisons: Sequence[SummaryComparison], arms: Mapping[str, int], notes: list[str]
) -> tuple[list[Table], list[list[Any]]]:
    """Tables and CSV rows of the modes' macro-averages; what is left out goes to `notes`."""
    tables, abl_rows = [], []
    subset_cols = [f"{SUBSET_TITLES[s]} %" for s in SUBSETS]
    for cmp in comparisons:
        n_single = sum(1 for t in cmp.tasks if subset_of(t, arms) == "single")
        rows = [
            [mode_label(m), runs_text(cmp.mode_runs[m])]
            + [mean_sd_text(cmp.macros[(m, s)]) for s in SUBSETS]
            for m in cmp.modes
        ]
        if OWN in cmp.modes:
            rows += [
                [f"{mode_label(m)} − own", ""] + [signed(cmp.delta(m, s)) for s in SUBSETS]
                for m in cmp.modes
                if m != OWN
            ]
        title = (
            f"{cmp.model} — {cmp.protocol}{suite_label(cmp.suite)}: summary source over "
            f"{len(cmp.tasks)} matched tasks "
            f"({n_single} single-arm, {len(cmp.tasks) - n_single} dual-arm)"
        )
        tables.append(Table(title, ["summary source", "runs", *subset_cols], rows))
        for m in cmp.modes:
            for s in SUBSETS:
                spread = cmp.macros[(m, s)]
                abl_rows.append(
                    [
                        cmp.model,
                        cmp.protocol,
                        cmp.suite,
                        m,
                        s,
                        len(cmp.tasks),
                        None if spread is None else spread.n,
                        None if spread is None else spread.mean,
                        None if spread is None else spread.sd,
                        cmp.delta(m, s) if OWN in cmp.modes and m != OWN else None,
                    ]
                )
        if cmp.left_out:
            notes.append(
                f"{cmp.model} / {cmp.protocol}{suite_label(cmp.suite)}: left out, not run under "
                "every summary mode: "
                f"{list(cmp.left_out)}"
            )
        if OWN not in cmp.modes:
            notes.append(
                f"{cmp.model} / {cmp.protocol}{suite_label(cmp.suite)}: no own-summary run, "
                "so no difference rows"
            )
    return tables, abl_rows


def _cross_model_tables(cross: Sequence[CrossModel]) -> tuple[list[Table], list[list[Any]]]:
    tables, cross_rows = [], []
    for cm in cross:
        header = ["evaluated model", "Own %"]
        for src in cm.sources:
            header += [f"on {src}: rate %", f"on {src}: Δ"]
        rows = []
        for r in cm.rows:
            row = [r.model, pct(r.own)]
            for src in cm.sources:
                row += [pct(r.shared[src]), signed(r.delta(src))] if src in r.shared else ["—", "—"]
            rows.append(row)
            cross_rows += [
                [cm.protocol, cm.suite, r.model, src, r.own, r.shared.get(src), r.delta(src)]
                for src in cm.sources
            ]
        avg = ["avg", pct(cm.avg_own)]
        for src in cm.sources:
            avg += [pct(cm.avg_rate(src)), signed(cm.avg_delta(src))]
        rows.append(avg)
        cross_rows += [
            [cm.protocol, cm.suite, "avg", src, cm.avg_own, cm.avg_rate(src), cm.avg_delta(src)]
            for src in cm.sources
        ]
        tables.append(
            Table(
                f"Shared summary sources — {cm.protocol}{suite_label(cm.suite)} (pooled success "
                "over each model's matched tasks and runs; Δ = shared − own; avg Δ leaves out "
                "the summary author)",
                header,
                rows,
            )
        )
    return tables, cross_rows


def _per_task_tables(
    comparisons: Sequence[SummaryComparison],
) -> tuple[list[Table], list[list[Any]]]:
    tables, task_rows = [], []
    for cmp in comparisons:
        rows = []
        for task in cmp.tasks:
            row = [task]
            for m in cmp.modes:
                k, n = cmp.counts.get((m, task), (0, 0))
                row.append(f"{pct(Fraction(k, n))} ({k}/{n})" if n else "—")
                task_rows.append(
                    [
                        cmp.model,
                        cmp.protocol,
                        cmp.suite,
                        task,
                        m,
                        k,
                        n,
                        Fraction(k, n) if n else None,
                    ]
                )
            rows.append(row)
        tables.append(
            Table(
                f"{cmp.model} — {cmp.protocol}{suite_label(cmp.suite)}: per-task success % by "
                "summary source "
                f"({runs_label(cmp.runs) if cmp.runs else 'no run under every mode'})",
                ["task", *[mode_label(m) for m in cmp.modes]],
                rows,
            )
        )
    return tables, task_rows


def learning_section(rows: Sequence[LearningRow]) -> Section | None:
    if not rows:
        return None
    display = [
        [
            r.model,
            r.family,
            r.status,
            r.stop_reason,
            str(r.model_calls),
            f"{r.frames_inspected}/{r.n_frames}",
            str(r.learn_refusals),
        ]
        for r in rows
    ]
    header = [
        "model",
        "family",
        "status",
        "stop reason",
        "model calls",
        "frames inspected",
        "learn refusals",
    ]
    csv_rows = [
        [
            r.model,
            r.family,
            r.status,
            r.stop_reason,
            r.model_calls,
            r.frames_inspected,
            r.n_frames,
            r.learn_refusals,
        ]
        for r in rows
    ]
    return Section(
        "learning_stage",
        "Learning stage",
        [Table(f"Demonstration-summary sessions (RUN_DIR/{SUMMARIES}/)", header, display)],
        [
            Csv(
                "learning_stage",
                [
                    "model",
                    "family",
                    "status",
                    "stop_reason",
                    "model_calls",
                    "frames_inspected",
                    "n_frames",
                    "learn_refusals",
                ],
                csv_rows,
            )
        ],
    )
