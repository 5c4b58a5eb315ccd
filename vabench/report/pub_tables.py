"""Sections of the paper's headline views (`publication`): overall success with the published
reference rows, the task-by-model matrix, and the capability profile; and the figures' inputs.

Reference rows carry `published.REFERENCE_SHORT` in their source column (report.html greys
such rows) and the sections' notes spell `published.REFERENCE_LABEL` out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from vabench.report import published as P
from vabench.report.publication import CRITERIA, Bars, Condition, Matrix, Profile, label
from vabench.report.stats import SUBSET_TITLES, SUBSETS, Spread
from vabench.tables import Csv, Section, Table, mean_sd_text, pct

OVERALL_TABLE = "Overall success per condition (%, mean ± sample SD across runs)"
MATRIX_TABLE = "Success per task and condition (%, mean ± sample SD across runs)"
REFERENCE_MATRIX_TABLE = f"Per-task success, {P.REFERENCE_LABEL}"
CAPABILITY_TABLE = "Capability profile per annotated condition (%)"
RUN_SOURCE = "this run"


def _pct_pair(s: Spread) -> tuple[float, float | None]:
    return (100 * float(s.mean), None if s.sd is None else 100 * s.sd)


def overall_bars(
    conditions: Sequence[Condition],
    spreads: Mapping[tuple[str, str, str], Spread],
    reference: bool,
    marks: Mapping[str, str] | None = None,
) -> list[Bars]:
    marks = marks or {}
    rows = [
        Bars(
            label(c, conditions),
            {s: _pct_pair(spreads[(*c, s)]) for s in SUBSETS if (*c, s) in spreads},
            mark=" *" if c[0] in marks else "",
        )
        for c in conditions
    ]
    if reference:
        rows += [Bars(m, dict(P.OVERALL[m]), reference=True) for m in P.MODELS]
    return rows


def overall_section(
    conditions: Sequence[Condition],
    spreads: Mapping[tuple[str, str, str], Spread],
    reference: bool,
    marks: Mapping[str, str] | None = None,
) -> Section:
    """`marks`: model -> what about its sweep does not match the others' (a leaderboard merged
    with --allow-mismatch); shown in a column of its own."""
    marks = marks or {}
    rows, csv_rows = [], []
    for c in conditions:
        model, track = c
        n_runs = max((spreads[(*c, s)].n for s in SUBSETS if (*c, s) in spreads), default=0)
        rows.append(
            [
                model,
                track,
                RUN_SOURCE,
                str(n_runs),
                *[mean_sd_text(spreads.get((*c, s))) for s in SUBSETS],
                marks.get(model, ""),
            ]
        )
        for s in SUBSETS:
            if (sp := spreads.get((*c, s))) is not None:
                csv_rows.append([model, track, RUN_SOURCE, s, sp.n, sp.mean, sp.sd])
    notes = [
        "per run, the unweighted mean of the per-task success rates over the single-arm, "
        "dual-arm or all families (the paper's eq. base-success); across runs, the mean and the "
        "sample SD (n - 1) of those run-level macro-averages",
        "conditions: models on a track of base families under the active protocol, best "
        "all-families mean first",
    ]
    if reference:
        for m in P.MODELS:
            values = P.OVERALL[m]
            rows.append(
                [
                    m,
                    "paper",
                    P.REFERENCE_SHORT,
                    "3",
                    *[f"{values[s][0]:.2f} ± {values[s][1]:.2f}" for s in SUBSETS],
                    "",
                ]
            )
            csv_rows += [
                [m, "paper", P.REFERENCE_SHORT, s, 3, values[s][0] / 100, values[s][1] / 100]
                for s in SUBSETS
            ]
        notes.append(f"grey rows: {P.REFERENCE_LABEL} ({P.SOURCE})")
    if marks:
        notes.append(
            "marked rows (*): merged with --allow-mismatch; their sweep differs from the "
            "first sweep in what the column names"
        )
    header = [
        "model",
        "track",
        "source",
        "runs",
        *[f"{SUBSET_TITLES[s]} %" for s in SUBSETS],
        "comparability",
    ]
    if not marks:
        header = header[:-1]
        rows = [r[:-1] for r in rows]
    return Section(
        "overall",
        "Overall success",
        [Table(OVERALL_TABLE, header, rows)],
        [Csv("overall", ["model", "track", "source", "subset", "runs", "mean", "sd"], csv_rows)],
        notes,
    )


def matrix_values(
    matrix: Matrix, labels: Mapping[Condition, str]
) -> dict[tuple[str, str], tuple[float, float | None]]:
    return {(task, labels[c]): _pct_pair(s) for (task, c), s in matrix.cells.items()}


def reference_matrix_values() -> dict[tuple[str, str], tuple[float, float | None]]:
    return {(t, m): P.PER_TASK[t][m] for t in P.PAPER_TASK_ORDER for m in P.MODELS}


def matrix_section(
    matrix: Matrix, labels: Mapping[Condition, str], arms: Mapping[str, int], reference: bool
) -> Section:
    header = ["task", "arms", *[labels[c] for c in matrix.conditions]]
    rows = [
        [
            task,
            "dual" if arms.get(task, 1) > 1 else "single",
            *[mean_sd_text(matrix.cells.get((task, c))) for c in matrix.conditions],
        ]
        for task in matrix.tasks
    ]
    csv_rows = [
        [c[0], c[1], RUN_SOURCE, task, s.n, s.mean, s.sd]
        for (task, c), s in sorted(matrix.cells.items())
    ]
    tables = [Table(MATRIX_TABLE, header, rows)]
    notes = ["tasks in the paper's row order (single-arm, then dual-arm); columns as Overall"]
    if reference:
        tables.append(
            Table(
                REFERENCE_MATRIX_TABLE,
                ["task", "source", *P.MODELS],
                [
                    [
                        t,
                        P.REFERENCE_SHORT,
                        *[f"{a:.2f} ± {b:.2f}" for a, b in P.PER_TASK[t].values()],
                    ]
                    for t in P.PAPER_TASK_ORDER
                ],
            )
        )
        csv_rows += [
            [
                m,
                "paper",
                P.REFERENCE_SHORT,
                t,
                3,
                P.PER_TASK[t][m][0] / 100,
                P.PER_TASK[t][m][1] / 100,
            ]
            for t in P.PAPER_TASK_ORDER
            for m in P.MODELS
        ]
        notes.append(f"grey rows: {P.REFERENCE_LABEL} ({P.SOURCE})")
    return Section(
        "task_matrix",
        "Task-by-model success",
        tables,
        [Csv("task_matrix", ["model", "track", "source", "task", "runs", "mean", "sd"], csv_rows)],
        notes,
    )


def capability_section(profiles: Sequence[Profile]) -> Section | None:
    if not profiles:
        return None
    rows = [
        [
            p.model,
            p.track,
            p.runs_text,
            str(p.episodes),
            *["NA" if (v := p.values[c]) is None else pct(v / 100) for c in CRITERIA],
        ]
        for p in profiles
    ]
    csv_rows = [
        [p.model, p.track, ",".join(map(str, p.runs)), c, p.n[c], p.values[c]]
        for p in profiles
        for c in CRITERIA
    ]
    return Section(
        "capability",
        "Capability profile (nine behavioural diagnostics)",
        [Table(CAPABILITY_TABLE, ["model", "track", "annotated", "episodes", *CRITERIA], rows)],
        [Csv("capability", ["model", "track", "runs", "criterion", "n", "percent"], csv_rows)],
        [
            "each criterion: the share of positive majority labels among its applicable "
            "annotated episodes, the same numbers as Behavioural diagnostics, Per condition",
            "ED, OC, PF: only episodes with an observable error (majority error gate 1); "
            "error-free episodes are NA and leave the denominator; AE: only episodes with an "
            "assessable ambiguity; NA: no applicable episode (a gap on the radar, not 0)",
            "the paper annotates one run per condition; annotations over several runs are "
            "pooled, and the runs named",
        ],
    )
