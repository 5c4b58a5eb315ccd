"""Sections of the report for the tracks beyond the base evaluation (statistics: `tracks`).

Each builder returns None when the sweep holds no data for it, so a base sweep's report keeps
exactly its base sections. Display tables show percentages with two decimals and differences
as signed points ("-10.00"); CSV files keep raw counts and rates in [0, 1].
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from fractions import Fraction

from vabench.report.stats import SUBSET_TITLES, SUBSETS, subset_of
from vabench.report.tables import (
    Csv,
    Section,
    Table,
    mean_sd_text,
    pct,
    runs_label,
    runs_text,
    signed,
)
from vabench.report.tracks import (
    OWN,
    CrossModel,
    LearningRow,
    LongHorizon,
    SummaryComparison,
    TransferComparison,
    suite_label,
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
    if not comparisons:
        return None
    tables, abl_rows, cross_rows, task_rows = [], [], [], []
    notes = list(notes)
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
        [Table("Demonstration-summary sessions (RUN_DIR/summaries/)", header, display)],
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


def transfer_section(comparisons: Sequence[TransferComparison]) -> Section | None:
    if not comparisons:
        return None
    tables, summary, fam_rows, macro_rows, notes = [], [], [], [], []
    for cmp in comparisons:
        cond = f"{cmp.model} — {cmp.protocol}, summaries {cmp.mode}"
        summary.append(
            [
                cmp.model,
                cmp.protocol,
                cmp.mode,
                str(len(cmp.families)),
                runs_text(cmp.runs),
                mean_sd_text(cmp.base),
                mean_sd_text(cmp.heldout),
                mean_sd_text(cmp.delta, sign=True),
            ]
        )
        rows = [
            [
                f.base,
                f.heldout,
                f"{pct(f.base_rate)} ({f.base_successes}/{f.base_total})",
                f"{pct(f.heldout_rate)} ({f.heldout_successes}/{f.heldout_total})",
                signed(f.delta) if f.skipped_side is None else f"— (all {f.skipped_side} skipped)",
            ]
            for f in cmp.families
        ]
        tables.append(
            Table(
                f"{cond}: per family ({runs_label(cmp.runs) if cmp.runs else 'no matched run'})",
                ["base family", "held-out task", "base %", "held-out %", "Δ"],
                rows,
            )
        )
        fam_rows += [
            [
                cmp.model,
                cmp.protocol,
                cmp.mode,
                f.base,
                f.heldout,
                f.base_mode,
                f.base_successes,
                f.base_total,
                f.heldout_successes,
                f.heldout_total,
                f.delta,
                f.base_skipped,
                f.heldout_skipped,
            ]
            for f in cmp.families
        ]
        for name, s in (("base", cmp.base), ("heldout", cmp.heldout), ("delta", cmp.delta)):
            macro_rows.append(
                [
                    cmp.model,
                    cmp.protocol,
                    cmp.mode,
                    name,
                    len(cmp.families),
                    len(cmp.runs),
                    None if s is None else s.mean,
                    None if s is None else s.sd,
                ]
            )
        if cmp.unmatched:
            notes.append(
                f"{cond}: left out, no base-family run under the same protocol and run: "
                f"{list(cmp.unmatched)}"
            )
        if cmp.skipped:
            notes.append(
                f"{cond}: left out of the macro-averages and shown without a Δ, every episode "
                "of the base or the held-out side skipped (the model stopped before its first "
                f"step), so the pair compares nothing: {list(cmp.skipped)}"
            )
        if any(f.base_mode != cmp.mode for f in cmp.families):
            notes.append(f"{cond}: base families taken from own-summary runs")
    tables.insert(
        0,
        Table(
            "Matched transfer: macro-average over matched families (mean ± sample SD across runs; "
            "Δ = held-out − base)",
            ["model", "protocol", "summaries", "families", "runs", "base %", "held-out %", "Δ"],
            summary,
        ),
    )
    return Section(
        "transfer",
        "Controlled transfer",
        tables,
        [
            Csv(
                "transfer",
                [
                    "model",
                    "protocol",
                    "mode",
                    "base_family",
                    "heldout_task",
                    "base_mode",
                    "base_successes",
                    "base_total",
                    "heldout_successes",
                    "heldout_total",
                    "delta_rate",
                    "base_skipped",
                    "heldout_skipped",
                ],
                fam_rows,
            ),
            Csv(
                "transfer_macro",
                ["model", "protocol", "mode", "quantity", "families", "runs", "mean", "sd"],
                macro_rows,
            ),
        ],
        notes,
    )


def long_horizon_section(results: Sequence[LongHorizon]) -> Section | None:
    if not results:
        return None
    rows, csv_rows = [], []
    for lh in results:
        for r in lh.runs:
            rows.append(
                [
                    lh.model,
                    lh.track,
                    lh.task,
                    str(r.run),
                    f"{r.placed}/{r.possible}",
                    pct(r.placed_rate),
                    f"{r.successes}/{r.episodes}",
                    pct(r.success_rate),
                ]
            )
            csv_rows.append(
                [
                    lh.model,
                    lh.track,
                    lh.task,
                    r.run,
                    r.episodes,
                    r.placed,
                    r.possible,
                    r.placed_rate,
                    r.successes,
                    r.success_rate,
                ]
            )
        placed = sum(r.placed for r in lh.runs)
        possible = sum(r.possible for r in lh.runs)
        rows.append(
            [
                lh.model,
                lh.track,
                lh.task,
                "mean",
                f"{placed}/{possible} in all",
                mean_sd_text(lh.placed),
                f"{sum(r.successes for r in lh.runs)}/{sum(r.episodes for r in lh.runs)} in all",
                mean_sd_text(lh.success),
            ]
        )
    header = [
        "model",
        "track",
        "task",
        "run",
        "objects placed",
        "objects %",
        "strict success",
        "success %",
    ]
    return Section(
        "long_horizon",
        "Long-horizon composition",
        [
            Table(
                "Objects placed (sum of progress, out of checkpoints × episodes); strict success",
                header,
                rows,
            )
        ],
        [
            Csv(
                "long_horizon",
                [
                    "model",
                    "track",
                    "task",
                    "run",
                    "episodes",
                    "placed",
                    "possible",
                    "placed_rate",
                    "successes",
                    "success_rate",
                ],
                csv_rows,
            )
        ],
    )
