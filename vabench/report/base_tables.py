"""Sections of the base evaluation: macro-averages, per-task success, active vs passive,
subtask checkpoints, usage (statistics: `stats`, `active_passive`; formatting: `tables`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from fractions import Fraction

from vabench.llm_pool.spend import Pricing, cost_cell, cost_text
from vabench.report.active_passive import TrackComparison, in_order
from vabench.report.stats import (
    SUBSET_TITLES,
    SUBSETS,
    Cell,
    Checkpoints,
    Macro,
    Spread,
    Usage,
    subset_of,
)
from vabench.run_layout import INFRASTRUCTURE
from vabench.tables import (
    Csv,
    Section,
    Table,
    mean_sd_text,
    p_value_text,
    pct,
    runs_label,
    signed,
)

MACRO_TABLE = "Macro-average success (mean ± sample SD across runs)"
"""Table titles double as the anchors of figures (report.html shows a figure beside its table)."""


def task_table_title(model: str, track: str) -> str:
    return f"{model} — {track}"


def comparison_table_title(cmp: TrackComparison) -> str:
    return f"{cmp.model} — {runs_label(cmp.runs)}"


def per_task_section(
    cells: Sequence[Cell],
    spreads: Mapping[tuple[str, str, str], Spread],
    arms: Mapping[str, int],
    order: Sequence[str],
) -> Section:
    rank = {t: i for i, t in enumerate(order)}
    tables = []
    for model, track in sorted({(c.model, c.track) for c in cells}):
        mine = [c for c in cells if (c.model, c.track) == (model, track)]
        runs = sorted({c.run for c in mine})
        tasks = sorted({c.task for c in mine}, key=lambda t: (rank.get(t, len(rank)), t))
        by = {(c.task, c.run): c for c in mine}
        rows = []
        for task in tasks:
            counts = [
                f"{by[(task, r)].successes}/{by[(task, r)].total}" if (task, r) in by else "—"
                for r in runs
            ]
            rows.append(
                [task, subset_of(task, arms), *counts, mean_sd_text(spreads[(model, track, task)])]
            )
        header = ["task", "arms", *[f"run {r}" for r in runs], "success % (mean ± SD)"]
        tables.append(Table(task_table_title(model, track), header, rows))
    csv_rows = [
        [c.model, c.track, c.task, subset_of(c.task, arms), c.run, c.successes, c.total, c.rate]
        for c in cells
    ]
    header = ["model", "track", "task", "arms", "run", "successes", "total", "rate"]
    return Section(
        "success_per_task",
        "Per-task success per run",
        tables,
        [Csv("success_per_task", header, csv_rows)],
    )


def macro_section(
    macros: Sequence[Macro], spreads: Mapping[tuple[str, str, str], Spread], notes: list[str]
) -> Section:
    pairs = sorted({(m.model, m.track) for m in macros})
    summary = []
    for model, track in pairs:
        n_runs = len({m.run for m in macros if (m.model, m.track) == (model, track)})
        summary.append(
            [model, track, str(n_runs)]
            + [mean_sd_text(spreads.get((model, track, s))) for s in SUBSETS]
        )
    by = {(m.model, m.track, m.run, m.subset): m for m in macros}
    per_run = []
    for model, track, run in sorted({(m.model, m.track, m.run) for m in macros}):
        ms = [by[(model, track, run, s)] for s in SUBSETS]
        per_run.append(
            [model, track, str(run)]
            + [pct(m.rate) for m in ms]
            + [f"{len(ms[0].families)}+{len(ms[1].families)}"]
        )
    subset_cols = [f"{SUBSET_TITLES[s]} %" for s in SUBSETS]
    tables = [
        Table(
            MACRO_TABLE,
            ["model", "track", "runs"] + subset_cols,
            summary,
        ),
        Table(
            "Run-level macro-averages",
            ["model", "track", "run", *subset_cols, "families (single+dual)"],
            per_run,
        ),
    ]
    run_rows = [[m.model, m.track, m.run, m.subset, len(m.families), m.rate] for m in macros]
    summary_rows = [
        [model, track, subset, s.n, s.mean, s.sd] for (model, track, subset), s in spreads.items()
    ]
    return Section(
        "macro_average",
        "Macro-average success",
        tables,
        [
            Csv("macro_average", ["model", "track", "subset", "runs", "mean", "sd"], summary_rows),
            Csv(
                "macro_average_runs",
                ["model", "track", "run", "subset", "families", "rate"],
                run_rows,
            ),
        ],
        notes,
    )


def active_passive_section(comparisons: Sequence[TrackComparison], order: Sequence[str]) -> Section:
    summary, tables, fam_rows, test_rows, notes = [], [], [], [], []
    for cmp in comparisons:
        families = in_order(cmp.families, order)
        label = runs_label(cmp.runs)
        summary.append(
            [
                cmp.model,
                label,
                str(len(cmp.families)),
                str(cmp.non_tied),
                str(cmp.passive_worse),
                str(cmp.passive_better),
                str(cmp.ties),
                p_value_text(cmp.p_value),
            ]
        )
        rows = [
            [
                p.task,
                f"{p.active}/{p.active_total}",
                f"{p.passive}/{p.passive_total}",
                _delta_text(p.passive - p.active, p.delta, p.active_total == p.passive_total)
                if p.skipped_side is None
                else f"— (all skipped under {p.skipped_side})",
            ]
            for p in families
        ]
        tables.append(
            Table(comparison_table_title(cmp), ["task", "active", "passive", "Δ (P − A)"], rows)
        )
        for p in families:
            fam_rows.append(
                [
                    cmp.model,
                    label,
                    p.task,
                    p.active,
                    p.active_total,
                    p.passive,
                    p.passive_total,
                    p.delta if p.skipped_side is None else None,
                    p.active_skipped,
                    p.passive_skipped,
                ]
            )
        test_rows.append(
            [
                cmp.model,
                label,
                len(cmp.families),
                cmp.non_tied,
                cmp.passive_worse,
                cmp.passive_better,
                cmp.ties,
                cmp.p_value,
            ]
        )
        if cmp.skipped:
            notes.append(
                f"{cmp.model} ({label}): left out of the sign test and shown without a Δ, "
                "every episode skipped (the model stopped before its first step) under one "
                f"protocol, so the pair compares nothing: {list(cmp.skipped)}"
                + ("" if cmp.p_value is not None else "; no family is left: no sign test")
            )
        if cmp.only_one_track:
            notes.append(
                f"{cmp.model} ({label}): left out, run under one track only: "
                f"{list(cmp.only_one_track)}"
            )
    head = [
        "model",
        "runs",
        "families",
        "non-tied",
        "passive worse",
        "passive better",
        "ties",
        "sign test p (two-sided)",
    ]
    tables.insert(0, Table("Sign test over non-tied families", head, summary))
    return Section(
        "active_passive",
        "Active vs passive camera protocol",
        tables if comparisons else [],
        [
            Csv(
                "active_passive",
                [
                    "model",
                    "runs",
                    "task",
                    "active",
                    "active_total",
                    "passive",
                    "passive_total",
                    "delta_rate",
                    "active_skipped",
                    "passive_skipped",
                ],
                fam_rows,
            ),
            Csv(
                "sign_test",
                [
                    "model",
                    "runs",
                    "families",
                    "non_tied",
                    "passive_worse",
                    "passive_better",
                    "ties",
                    "p_value",
                ],
                test_rows,
            ),
        ],
        notes or ([] if comparisons else ["no model was run under both active and passive"]),
    )


def _delta_text(count: int, rate: Fraction, same_totals: bool) -> str:
    pp = f"{signed(rate)} pp"
    return f"{count:+d} ({pp})" if same_totals else pp


def checkpoint_section(points: Sequence[Checkpoints]) -> Section:
    by = {(c.model, c.track, c.subset): c for c in points}
    rows = []
    for model, track in sorted({(c.model, c.track) for c in points}):
        cells = []
        for s in SUBSETS:
            c = by.get((model, track, s))
            cells.append("—" if c is None else f"{c.reached}/{c.possible} ({pct(c.rate)})")
        rows.append([model, track, *cells])
    header = ["model", "track", *[f"{SUBSET_TITLES[s]} reached/possible (%)" for s in SUBSETS]]
    csv_rows = [[c.model, c.track, c.subset, c.reached, c.possible, c.rate] for c in points]
    return Section(
        "checkpoints",
        "Subtask checkpoints (micro-average over scored episodes)",
        [Table("Checkpoints reached / possible", header, rows)],
        [Csv("checkpoints", ["model", "track", "subset", "reached", "possible", "rate"], csv_rows)],
    )


def usage_section(
    usages: Sequence[Usage],
    unscored: Mapping[tuple[str, str, str], tuple[int, float]],
    unresolved_count: int,
    retried: Mapping[tuple[str, str], int],
    pricing: Mapping[str, Pricing] | None = None,
) -> Section:
    """`pricing`: how each model's cost is shown (`llm_pool.spend.cost_text`); a model not in
    it shows dollars."""
    known = pricing or {}

    def share(x: float | None) -> str:
        return "—" if x is None else f"{100 * x:.1f}%"

    def usd(value: float, model: str, fmt: str = ".2f") -> str:
        return cost_text(value, {model: known[model]} if model in known else {}, fmt, sign="")

    rows = [
        [
            u.model,
            u.track,
            str(u.episodes),
            f"{u.mean_steps:.1f}",
            share(u.camera_share),
            share(u.invalid_output_share),
            share(u.invalid_action_share),
            f"{u.total_tokens:,}",
            f"{u.total_tokens / u.episodes:,.0f}",
            usd(u.cost_usd, u.model),
            usd(u.cost_usd / u.episodes, u.model, ".4f"),
        ]
        for u in usages
    ]
    header = [
        "model",
        "track",
        "episodes",
        "mean steps",
        "camera actions / steps",
        "invalid outputs / calls",
        "invalid actions / robot actions",
        "tokens",
        "tokens / episode",
        "cost USD",
        "cost USD / episode",
    ]
    tables = [Table("Usage over scored episodes", header, rows)]
    if unscored:
        tables.append(
            Table(
                "Unscored records (not counted in any statistic)",
                ["model", "track", "status", "records", "cost USD"],
                [[m, t, s, str(n), usd(c, m)] for (m, t, s), (n, c) in unscored.items()],
            )
        )
    token_names = list(usages[0].tokens) if usages else []
    csv_rows = [
        [
            u.model,
            u.track,
            u.episodes,
            u.steps_used,
            u.mean_steps,
            u.robot_actions,
            u.camera_actions,
            u.camera_share,
            u.model_calls,
            u.invalid_outputs,
            u.invalid_output_share,
            u.invalid_actions,
            u.invalid_action_share,
            *[u.tokens[n] for n in token_names],
            cost_cell(u.cost_usd, known.get(u.model)),
            cost_cell(u.cost_usd / u.episodes, known.get(u.model)),
        ]
        for u in usages
    ]
    csv_header = [
        "model",
        "track",
        "episodes",
        "steps_used",
        "mean_steps",
        "robot_actions",
        "camera_actions",
        "camera_share",
        "model_calls",
        "invalid_outputs",
        "invalid_output_share",
        "invalid_actions",
        "invalid_action_share",
        *[f"tokens_{n}" for n in token_names],
        "cost_usd",
        "cost_usd_per_episode",
    ]
    notes = []
    if unresolved_count:
        notes.append(
            f"{unresolved_count} planned episode(s) have only unscored records "
            "(never scored; not in any statistic)"
        )
    if retried:
        runs_again = "; ".join(f"{m} / {t}: {n}" for (m, t), n in retried.items())
        notes.append(f"infrastructure failures run again ({INFRASTRUCTURE}): {runs_again}")
    return Section(
        "usage",
        "Steps, actions, tokens and cost",
        tables,
        [
            Csv("usage", csv_header, csv_rows),
            Csv(
                "unscored",
                ["model", "track", "status", "records", "cost_usd"],
                [
                    [m, t, s, n, cost_cell(c, known.get(m))]
                    for (m, t, s), (n, c) in unscored.items()
                ],
            ),
        ],
        notes,
    )
