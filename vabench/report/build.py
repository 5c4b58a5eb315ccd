"""Assembling and writing RUN_DIR/report/ from RUN_DIR/results.jsonl.

Files written (each atomically: a temporary sibling, then `os.replace`):
    report.md            every table, with the notes and the figures linked
    <section>.md         one file per topic (overall, task_matrix, capability (with
                         annotations): the paper's headline views, `publication`;
                         success_per_task, macro_average, active_passive, checkpoints,
                         usage, spend; and, only when the sweep holds their data,
                         summary_source, learning_stage, transfer, long_horizon; and,
                         when RUN_DIR/annotations/ holds judgments, diagnostics, agreement,
                         vote_rules)
    <table>.csv          raw numbers in long format
    results.json         every episode, the aggregates and the provenance, schema-checked
                         (`results_file`, docs/RESULTS.md); episode_outcomes.csv its episodes
    figures/*.png        overall bars, task matrix (and the published one), capability radars
                         (a sheet, and one per condition for the viewer), macro-average bars,
                         per-task bars per model/track, active vs passive
    report.html          everything above in one self-contained page (figures as base64), with
                         a table of contents and each figure beside the table it draws
An unfinished sweep (fewer scored episodes than RUN_DIR/plan.json planned) is said first, in
report.md, report.html and the printed summary, before any number it qualifies.
figures/ is wholly generated: PNGs of an earlier report that this one does not produce are
removed, so the folder never shows a model that is no longer in the results.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from vabench import tables
from vabench.report import (
    active_passive,
    base_tables,
    html,
    pub_tables,
    publication,
    published,
    results_file,
    spend,
    stats,
    suite_tables,
    suites,
    summaries,
    summary_tables,
)
from vabench.report.conditions import TaskMeta, condition_cells
from vabench.run_layout import FIGURES, REPORT_HTML, REPORT_MD, RunDir
from vabench.run_records import Results, load_results

if TYPE_CHECKING:
    from vabench.diagnostics.sections import DiagnosticsData


@dataclass(frozen=True)
class Board:
    """What a leaderboard over several sweeps adds to their merged results (`leaderboard`)."""

    reference: bool
    profiles: tuple[publication.Profile, ...] = ()
    marks: Mapping[str, str] = field(default_factory=dict)
    """model -> the comparability fields its sweep differs in (--allow-mismatch)."""
    sources: tuple[Mapping[str, Any], ...] = ()
    """Each merged run directory's `results_file.provenance`."""
    alerts: tuple[str, ...] = ()
    """What a reader must know first about each merged sweep (an unfinished one)."""


@dataclass
class ReportOutput:
    directory: Path
    files: list[Path]
    summary: list[str]


def task_arms() -> tuple[dict[str, int], list[str], tuple[str, ...]]:
    """Arms per registered task, the registry's task order, and the base families."""
    from vabench.tasks import BASE_FAMILIES, REGISTRY  # imports the task modules (jax): lazy

    return {n: len(t.arms) for n, t in REGISTRY.items()}, list(REGISTRY), BASE_FAMILIES


def task_meta() -> TaskMeta:
    """Suite of every registered task and the base family of each held-out variant."""
    from vabench.tasks import REGISTRY  # imports the task modules (jax): lazy

    return TaskMeta(
        suite={n: t.suite for n, t in REGISTRY.items()},
        base_family={n: t.base_family for n, t in REGISTRY.items() if t.base_family},
    )


def generate(run_dir: Path | str) -> ReportOutput:
    """Read RUN_DIR/results.jsonl, compute every statistic, write RUN_DIR/report/."""
    run_dir = Path(run_dir)
    results = load_results(run_dir)
    arms, order, base = task_arms()
    return write_report(RunDir(run_dir).report, results, arms, order, base, task_meta())


def make_report(run_dir: Path) -> Path:
    """The sweep's last step: write RUN_DIR/report/ and return that directory."""
    return generate(run_dir).directory


def write_report(
    out_dir: Path,
    results: Results,
    arms: Mapping[str, int],
    order: Sequence[str],
    base: Sequence[str],
    meta: TaskMeta | None = None,
    board: Board | None = None,
) -> ReportOutput:
    """`meta` (suites, base families) enables the transfer and long-horizon sections; the
    learning-stage section reads RUN_DIR/summaries/ next to the results file. `board`: the
    results merge several sweeps (`leaderboard`): their capability profiles, provenance and
    marks come from it, and the sections that read one run directory's files (diagnostics
    tables, learning stage, bill) are left out."""
    run_dir = results.path.parent
    one_dir = board is None
    data = load_diagnostics(run_dir) if board is None else None
    if board is None:
        reference, profiles, marks = reference_wanted(run_dir), publication.profiles(data), {}
    else:
        reference, profiles, marks = board.reference, list(board.profiles), dict(board.marks)
    cells = stats.task_cells(results.scored)
    pricing = spend.model_pricing(results.path.parent)
    task_spreads = stats.task_spread(cells)
    macros = stats.macro_averages(cells, arms)
    macro_spreads = stats.macro_spread(macros)
    comparisons = active_passive.track_comparisons(cells)
    unscored = stats.unscored_counts(results.unscored)
    unresolved = stats.unresolved(results.scored, results.unscored)

    n_single = sum(1 for t in base if t in arms and arms[t] == 1)
    n_dual = sum(1 for t in base if t in arms and arms[t] > 1)
    macro_notes = [
        f"base families (vabench.tasks): {n_single} single-arm, {n_dual} dual-arm "
        "(dual-arm = the task uses more than one arm)",
        *stats.coverage_notes(cells, base),
        *(results_file.api_setting_notes(run_dir) if one_dir else []),
    ]
    if results.truncated_tail:
        macro_notes.append(
            f"{results.path.name}: a truncated last line (a crash mid-write) was ignored"
        )
    conditions = publication.ranked(
        publication.primary_conditions(results.scored, base), macro_spreads
    )
    labels = {
        c: publication.label(c, conditions) + (" *" if c[0] in marks else "") for c in conditions
    }
    matrix = publication.task_matrix(cells, task_spreads, conditions)
    rank = {c: i for i, c in enumerate(conditions)}
    primary = [p for p in profiles if (p.model, p.track) in rank]
    radars = sorted(primary, key=lambda p: rank[(p.model, p.track)]) if primary else profiles
    sections = [
        pub_tables.overall_section(conditions, macro_spreads, reference, marks),
        pub_tables.matrix_section(matrix, labels, arms, reference),
        *([s] if (s := pub_tables.capability_section(radars)) is not None else []),
        base_tables.macro_section(macros, macro_spreads, macro_notes),
        base_tables.per_task_section(cells, task_spreads, arms, order),
        base_tables.active_passive_section(comparisons, order),
        *track_sections(results, arms, meta, learning=one_dir),
        base_tables.checkpoint_section(stats.checkpoint_micro(results.scored, arms)),
        *([] if data is None else diagnostic_sections(data)),
        base_tables.usage_section(
            stats.usage(results.scored), unscored, len(unresolved), results.retried, pricing
        ),
    ]
    bill_section = spend.spend_section(spend.bill(run_dir), pricing) if one_dir else None
    if bill_section is not None:
        sections.append(bill_section)

    # matplotlib (~0.7 s to import) only when a report is drawn: the sweep imports this
    # package at its start for the bill (`spend`)
    from vabench.report import figures, pub_figures

    dual = [t for t in matrix.tasks if arms.get(t, 1) > 1]
    pngs: list[tuple[str, html.Figure]] = [  # (its file in figures/, the figure)
        (
            "overall.png",
            html.Figure(
                "overall",
                "Overall success per condition",
                pub_figures.overall_figure(
                    pub_tables.overall_bars(conditions, macro_spreads, reference, marks)
                ),
                pub_tables.OVERALL_TABLE,
            ),
        ),
        (
            "task_matrix.png",
            html.Figure(
                "task_matrix",
                "Success per task and condition",
                pub_figures.heatmap_figure(
                    matrix.tasks,
                    [labels[c] for c in conditions],
                    pub_tables.matrix_values(matrix, labels),
                    "Success per task and condition (%, mean ± SD across runs)",
                    dual,
                ),
                pub_tables.MATRIX_TABLE,
            ),
        ),
    ]
    if reference:
        pngs.append(
            (
                "task_matrix_published.png",
                html.Figure(
                    "task_matrix",
                    f"Per-task success, {published.REFERENCE_LABEL}",
                    pub_figures.heatmap_figure(
                        published.PAPER_TASK_ORDER,
                        published.MODELS,
                        pub_tables.reference_matrix_values(),
                        f"Per-task success, {published.REFERENCE_SHORT}:\n"
                        "a different simulator, robot and seeds; not directly comparable",
                        published.PAPER_TASK_ORDER[-3:],
                        reference=True,
                    ),
                    pub_tables.REFERENCE_MATRIX_TABLE,
                ),
            )
        )
    if profiles:
        pngs.append(
            (
                "capability_radar.png",
                html.Figure(
                    "capability",
                    "Capability profile per annotated condition",
                    pub_figures.radar_sheet(radars),
                    pub_tables.CAPABILITY_TABLE,
                ),
            )
        )
        for p in profiles:
            pngs.append(
                (
                    radar_file(p.model, p.track),
                    html.Figure(
                        "",
                        f"{p.model} — {p.track}: capability profile",
                        pub_figures.radar_figure(p),
                    ),
                )
            )
    pngs += [
        (
            "macro_average.png",
            html.Figure(
                "macro_average",
                "Macro-average success",
                figures.macro_figure(macro_spreads),
                base_tables.MACRO_TABLE,
            ),
        )
    ]
    for model, track in sorted({(c.model, c.track) for c in cells}):
        figure = figures.task_success_figure(cells, task_spreads, model, track, order)
        pngs.append(
            (
                f"success_{_slug(model)}_{_slug(track)}.png",
                html.Figure(
                    "success_per_task",
                    f"{model} — {track}: per-task success",
                    figure,
                    base_tables.task_table_title(model, track),
                ),
            )
        )
    shown: dict[str, active_passive.TrackComparison] = {}
    for cmp in comparisons:  # the pooled comparison, when there is one, comes last per model
        shown[cmp.model] = cmp
    for model, cmp in shown.items():
        pngs.append(
            (
                f"active_passive_{_slug(model)}.png",
                html.Figure(
                    "active_passive",
                    f"{model}: active vs passive ({tables.runs_label(cmp.runs)})",
                    figures.active_passive_figure(cmp, order),
                    base_tables.comparison_table_title(cmp),
                ),
            )
        )

    alerts = _alerts(results, len(unresolved)) if board is None else list(board.alerts)
    summary = _summary(results, macro_spreads, comparisons, len(unresolved))
    written: list[Path] = []
    fig_dir = out_dir / FIGURES
    fig_dir.mkdir(parents=True, exist_ok=True)
    for name, f in pngs:
        written.append(_write(fig_dir / name, f.png))
    keep = {name for name, _ in pngs}
    for stale in fig_dir.glob("*.png"):
        if stale.name not in keep:
            stale.unlink()
    md_parts = [
        "# VA-Bench report\n",
        "".join(f"- **{a}**\n" for a in alerts) + "".join(f"- {s}\n" for s in summary),
    ]
    for section in sections:
        text = tables.section_markdown(section)
        written.append(_write(out_dir / f"{section.name}.md", text.encode()))
        links = [f"![{f.title}]({FIGURES}/{n})\n" for n, f in pngs if f.section == section.name]
        md_parts += [text, *links]
        for table in section.csvs:
            written.append(_write(out_dir / f"{table.name}.csv", tables.to_csv(table).encode()))
    everything = sorted(results.scored + results.unscored, key=results_file.sort_key)
    sources = (
        [results_file.provenance(run_dir, everything)] if board is None else list(board.sources)
    )
    doc = results_file.document(
        everything, cells, task_spreads, macros, macro_spreads, sources, reference, marks
    )
    written.append(_write(out_dir / results_file.RESULTS_FILE, json.dumps(doc, indent=1).encode()))
    episodes_csv = tables.Csv(
        results_file.EPISODES_CSV,
        results_file.EPISODE_COLUMNS,
        results_file.episode_csv_rows(everything),
    )
    written.append(
        _write(out_dir / f"{episodes_csv.name}.csv", tables.to_csv(episodes_csv).encode())
    )
    written.append(_write(out_dir / REPORT_MD, "\n".join(md_parts).encode()))
    page = html.render(
        "VA-Bench report",
        summary,
        sections,
        [f for _, f in pngs],
        alerts,
    )
    written.append(_write(out_dir / REPORT_HTML, page.encode()))
    return ReportOutput(out_dir, written, alerts + summary)


def track_sections(
    results: Results, arms: Mapping[str, int], meta: TaskMeta | None, learning: bool = True
) -> list[tables.Section]:
    """Summary source, learning stage, transfer and long horizon: those with data only."""
    cells, notes = condition_cells(results.scored)
    comparisons, more = summaries.summary_comparisons(
        cells, arms, None if meta is None else meta.suite
    )
    sections = [
        summary_tables.summary_section(
            comparisons,
            summaries.cross_model(comparisons),
            arms,
            notes + more + summaries.failed_summary_notes(results.scored),
        ),
    ]
    if learning:
        sections.append(
            summary_tables.learning_section(summaries.learning_rows(RunDir(results.path.parent)))
        )
    if meta is not None:
        sections += [
            suite_tables.transfer_section(suites.transfer_comparisons(cells, meta)),
            suite_tables.long_horizon_section(suites.long_horizon(results.scored, meta)),
        ]
    return [s for s in sections if s is not None]


def load_diagnostics(run_dir: Path) -> DiagnosticsData | None:
    """The run's annotations (RUN_DIR/annotations/, written by `python -m vabench.view` and
    the judge), collected; None when it holds none."""
    from vabench.diagnostics import sections as diagnostics

    if not RunDir(run_dir).annotations.is_dir():
        return None
    return diagnostics.load(run_dir)


def diagnostic_sections(data: DiagnosticsData) -> list[tables.Section]:
    """The nine behavioural diagnostics, agreement and vote-rule sensitivity."""
    from vabench.diagnostics import sections as diagnostics

    return diagnostics.sections(data)


def reference_wanted(run_dir: Path) -> bool:
    """`report.reference` of the run's sweep.yaml (default true: the published rows shown).
    Read as YAML: the report sits below the config package."""
    try:
        doc = yaml.safe_load(RunDir(run_dir).config.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return True
    section = doc.get("report") if isinstance(doc, dict) else None
    value = section.get("reference", True) if isinstance(section, dict) else True
    return value is not False


def radar_file(model: str, track: str) -> str:
    """The PNG of one condition's radar in figures/ (the viewer shows it beside its episodes)."""
    return f"radar_{_slug(model)}_{_slug(track)}.png"


def macro_headline(s: stats.Spread) -> str:
    """ "45.83 ± 5.89 % (mean ± SD over 2 runs)", or "8.33 % (1 run)": the unit after the
    number, the runs after both."""
    if s.sd is None:
        return f"{tables.pct(s.mean)} % ({s.n} run)"
    return f"{tables.pct(s.mean)} ± {tables.pct(s.sd)} % (mean ± SD over {s.n} runs)"


def planned_episodes(run: RunDir) -> int | None:
    """How many episodes the sweep planned (RUN_DIR/plan.json, written before the first
    episode); None without a readable plan (a run directory made by hand, or by an old
    sweep)."""
    try:
        plan = json.loads(run.plan.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    episodes = plan.get("episodes") if isinstance(plan, dict) else plan  # version 1: a list
    return len(episodes) if isinstance(episodes, list) else None


def sweep_alerts(results: Results) -> list[str]:
    """`_alerts` of one sweep's results."""
    return _alerts(results, len(stats.unresolved(results.scored, results.unscored)))


def _alerts(results: Results, n_unresolved: int) -> list[str]:
    """What a reader must know before any number: an unfinished sweep's numbers cover only the
    episodes scored so far, so they can move anywhere when it finishes."""
    planned = planned_episodes(RunDir(results.path.parent))
    scored = len(results.scored)
    if planned is None or scored >= planned:
        return []
    unscored = f" ({n_unresolved:,} more ended without a score)" if n_unresolved else ""
    return [
        f"incomplete sweep: {scored:,} of {planned:,} planned episodes scored{unscored}; "
        "every number below covers only those"
    ]


def _summary(
    results: Results,
    spreads: Mapping[tuple[str, str, str], stats.Spread],
    comparisons: Sequence[active_passive.TrackComparison],
    n_unresolved: int,
) -> list[str]:
    lines = [
        f"{len(results.scored)} scored episodes, {len(results.unscored)} unscored records "
        f"({n_unresolved} episodes never scored) in {results.path}"
    ]
    for (model, track, subset), s in spreads.items():
        if subset == "all":
            lines.append(f"{model} / {track}: macro-average success {macro_headline(s)}")
    for cmp in comparisons:
        left_out = (
            f" ({len(cmp.skipped)} families left out: every episode skipped under one protocol)"
            if cmp.skipped
            else ""
        )
        if cmp.p_value is None:
            lines.append(
                f"{cmp.model} active vs passive ({tables.runs_label(cmp.runs)}): no sign test, "
                "every family was skipped (stopped before its first step) under one protocol"
            )
            continue
        lines.append(
            f"{cmp.model} active vs passive ({tables.runs_label(cmp.runs)}): passive worse on "
            f"{cmp.passive_worse} of {cmp.non_tied} non-tied families, sign test "
            f"p = {tables.p_value_text(cmp.p_value)}{left_out}"
        )
    return lines


def _slug(name: str) -> str:
    """A file-name-safe form; a hash keeps names apart that differ only in unsafe characters."""
    slug = re.sub(r"[^A-Za-z0-9._-]+", "_", name)
    if slug != name:
        slug += "-" + hashlib.sha1(name.encode()).hexdigest()[:6]
    return slug


def _write(path: Path, data: bytes) -> Path:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return path
