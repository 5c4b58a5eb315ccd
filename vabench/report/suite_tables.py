"""Sections on the suites beyond the base evaluation, controlled transfer and long-horizon
composition (statistics: `suites`; number formats: `tables`); None for a suite the sweep did
not run."""

from __future__ import annotations

from collections.abc import Sequence

from vabench.report.suites import LongHorizon, TransferComparison
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
