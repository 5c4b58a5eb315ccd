"""The diagnostics sections of the report (and of `python -m vabench.diagnostics RUN_DIR`),
from RUN_DIR/annotations/.

Three sections, present only when the run holds annotations:
    diagnostics   the nine criteria and three module means per condition (model x track) and
                  per task, majority vote, NA excluded from denominators
    agreement     the paper's agreement table: n, unanimity, positive rate, Fleiss' kappa,
                  Gwet's AC1 per criterion, all criteria, all but FG
    vote_rules    strict / majority / permissive: mean over the nine criteria per condition,
                  the rankings, and Spearman / Kendall between the rules' orderings
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from vabench.diagnostics import aggregate as agg
from vabench.diagnostics.criteria import CRITERION_CODES, MODULE_CRITERIA, MODULES
from vabench.diagnostics.episodes import RunIndex
from vabench.diagnostics.stats import VOTE_RULES
from vabench.diagnostics.store import AnnotationStore, current
from vabench.tables import Csv, Section, Table, pct

MAX_PROBLEMS_SHOWN = 10
__all__ = ["load", "sections"]


@dataclass
class DiagnosticsData:
    index: RunIndex
    collected: agg.Collected
    problems: list[str]
    annotators: list[str]


def load(run_dir: Path | str, index: RunIndex | None = None) -> DiagnosticsData | None:
    """The run's annotations, collected; None when it has none."""
    index = index or RunIndex.load(run_dir)
    store = AnnotationStore(index)
    loaded = store.load()
    if not loaded.judgments and not loaded.problems:
        return None
    collected = agg.collect(index, current(loaded.judgments))
    annotators = sorted({j.annotator for j in loaded.judgments})
    return DiagnosticsData(index, collected, loaded.problems, annotators)


def sections(data: DiagnosticsData) -> list[Section]:
    return [diagnostics_section(data), agreement_section(data), vote_rule_section(data)]


def _num(x: float | None, digits: int = 3) -> str:
    return "—" if x is None else f"{x:.{digits}f}"


def _module_text(s: agg.Score) -> str:
    if s.value is None:
        return "NA"
    text = pct(s.value)
    return text if s.n == s.of else f"{text} ({s.n}/{s.of})"


def _score_rows(
    scores: Mapping[agg.Group, Mapping[str, agg.Score]], episodes: Mapping[agg.Group, int]
) -> tuple[list[list[str]], list[list[object]]]:
    rows, csv_rows = [], []
    for group, by_criterion in scores.items():
        modules = agg.module_scores(by_criterion)
        cells = [
            "NA" if by_criterion[c].value is None else pct(by_criterion[c].value)
            for c in CRITERION_CODES
        ]
        rows.append(
            [
                *group,
                str(episodes.get(group, 0)),
                *cells,
                *[_module_text(modules[m]) for m in MODULES],
            ]
        )
        task = group[2] if len(group) > 2 else ""
        for c in CRITERION_CODES:
            s = by_criterion[c]
            csv_rows.append([group[0], group[1], task, c, "majority", s.n, s.value])
        for m in MODULES:
            s = modules[m]
            csv_rows.append([group[0], group[1], task, m, "majority", s.n, s.value])
    return rows, csv_rows


def diagnostics_section(data: DiagnosticsData) -> Section:
    c, index = data.collected, data.index
    header = [*CRITERION_CODES, *MODULES]
    by_condition = agg.criterion_scores(c, index, agg.condition_of)
    by_task = agg.criterion_scores(c, index, agg.task_group_of)
    n_condition: dict[agg.Group, int] = {}
    n_task: dict[agg.Group, int] = {}
    for episode in c.gates:
        ref = index.episodes[episode]
        g = agg.condition_of(ref)
        n_condition[g] = n_condition.get(g, 0) + 1
        t = agg.task_group_of(ref)
        n_task[t] = n_task.get(t, 0) + 1
    rows_c, csv_c = _score_rows(by_condition, n_condition)
    rows_t, csv_t = _score_rows(by_task, n_task)
    missing = sum(i.status == "missing" for i in c.items)
    notes = [
        f"{len(c.gates)} annotated scored episodes, annotators: {', '.join(data.annotators)}",
        "each label is the majority vote of the episode's judgments; ED, OC, PF (error gate) "
        "and AE (ambiguity gate) are NA where the majority gate is 0 and leave the denominator",
        "modules: equal-weight mean of "
        + "; ".join(f"{m} = {'/'.join(cs)}" for m, cs in MODULE_CRITERIA.items())
        + "; '(2/3)' marks a mean over the criteria that have a score",
    ]
    if missing:
        notes.append(f"{missing} episode-criterion items not judged yet (not in any denominator)")
    if c.dropped:
        notes.append(f"{c.dropped} judgments of gated criteria dropped: their majority gate is 0")
    notes += problem_notes(data.problems)
    csv_header = ["model", "track", "task", "criterion", "rule", "n", "rate"]
    return Section(
        "diagnostics",
        "Behavioural diagnostics (%, majority vote of annotators)",
        [
            Table("Per condition", ["model", "track", "episodes", *header], rows_c),
            Table("Per task", ["model", "track", "task", "episodes", *header], rows_t),
        ],
        [Csv("diagnostics", csv_header, csv_c + csv_t)],
        notes,
    )


def problem_notes(problems: Sequence[str]) -> list[str]:
    if not problems:
        return []
    shown = [f"skipped: {p}" for p in problems[:MAX_PROBLEMS_SHOWN]]
    if len(problems) > MAX_PROBLEMS_SHOWN:
        shown.append(f"... and {len(problems) - MAX_PROBLEMS_SHOWN} more malformed lines")
    return shown


def agreement_section(data: DiagnosticsData) -> Section:
    return agreement_of(data.collected)


def agreement_of(collected: agg.Collected, notes: Sequence[str] = ()) -> Section:
    """The agreement section of collected judgments (a run's, or a votes file's), `notes`
    first."""
    rows, left_out = agg.agreement(collected)
    raters = agg.raters_of(collected)
    table_rows: list[list[str]] = []
    csv_rows: list[list[object]] = []
    notes = [
        *notes,
        f"items judged by exactly {raters or 0} annotators (n = applicable episode-"
        "criterion items); positive rate = share of majority labels equal to 1",
    ]
    for r in rows:
        table_rows.append(
            [
                r.module,
                r.label,
                str(r.n),
                pct(r.unanimity),
                _num(r.positive_rate),
                _num(r.kappa),
                _num(r.ac1),
            ]
        )
        csv_rows.append([r.module, r.label, r.n, r.unanimity, r.positive_rate, r.kappa, r.ac1])
        if r.kappa_note and r.n:
            notes.append(f"{r.label}: Fleiss' kappa {r.kappa_note}")
    if left_out:
        notes.append(f"{left_out} scored items with another number of judgments left out")
    header = ["module", "criterion", "n", "unanimity (%)", "pos. rate", "Fleiss kappa", "Gwet AC1"]
    return Section(
        "agreement",
        "Inter-annotator agreement",
        [Table("Agreement over the nine criteria", header, table_rows)],
        [
            Csv(
                "agreement",
                [
                    "module",
                    "criterion",
                    "n",
                    "unanimity",
                    "positive_rate",
                    "fleiss_kappa",
                    "gwet_ac1",
                ],
                csv_rows,
            )
        ],
        list(dict.fromkeys(notes)),
    )


def vote_rule_section(data: DiagnosticsData) -> Section:
    s = agg.sensitivity(data.collected, data.index)
    rows, csv_rows = [], []
    for group, means in s.means.items():
        values = [v for v in means.values() if v is not None]
        spread = max(values) - min(values) if values else None
        rows.append([*group, *[pct(means[r]) for r in VOTE_RULES], pct(spread)])
        csv_rows += [[*group, r, means[r]] for r in VOTE_RULES]
    rank_rows = [[r, " > ".join("/".join(g) for g in s.rankings[r]) or "—"] for r in VOTE_RULES]
    corr_rows = [[f"{a} vs {b}", _num(rho), _num(tau)] for a, b, rho, tau in s.correlations]
    notes = [
        "mean over the nine criteria per condition; strict credits a criterion only when every "
        "judgment is positive, permissive when any is; gates stay majority-voted",
    ]
    if s.note:
        notes.append(s.note)
    elif any(rho is None for _, _, rho, _ in s.correlations):
        notes.append("rank correlations need at least two conditions with different means")
    return Section(
        "vote_rules",
        "Vote-rule sensitivity",
        [
            Table(
                "Mean over the nine criteria (%)", ["model", "track", *VOTE_RULES, "range"], rows
            ),
            Table("Ranking of conditions", ["rule", "order (best first)"], rank_rows),
            Table(
                "Rank correlation between rules",
                ["rules", "Spearman rho", "Kendall tau"],
                corr_rows,
            ),
        ],
        [Csv("vote_rules", ["model", "track", "rule", "mean"], csv_rows)],
        notes,
    )
