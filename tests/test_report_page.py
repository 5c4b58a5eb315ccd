"""What a reader sees first: an unfinished sweep says so before any number, the
headline reads "number unit (runs)", each learning session is one row, the macro figure's
legend stays true when a subset has no data, and report.html has margins, a table of contents
and each figure beside its table. Hand-made records and task maps, as in test_report_tracks."""

from __future__ import annotations

import csv
import json
import re
import shutil
from pathlib import Path

import pytest

from vabench.report import figures, load_results
from vabench.report.build import write_report
from vabench.run_records import Record

SINGLE, OTHER, DUAL = "task_a1", "task_a2", "task_dual"
ARMS = {SINGLE: 1, OTHER: 1, DUAL: 2}
ORDER = [SINGLE, OTHER, DUAL]


def line(model: str, track: str, task: str, seed: int, run: int, success: bool) -> dict:
    return {
        "v": 1,
        "track": track,
        "episode_dir": f"episodes/{model}/{track}/{task}/seed_{seed}/run_{run}",
        "task": task,
        "seed": seed,
        "model": model,
        "protocol": track,
        "run": run,
        "status": "success" if success else "failure",
        "success": success,
        "stop_reason": "success" if success else "budget_exhausted",
        "step_budget": 50,
        "n_checkpoints": 3,
    }


def pattern(model: str, track: str, run: int, successes: dict[str, int], seeds: int = 4):
    return [
        line(model, track, task, seed, run, seed < k)
        for task, k in successes.items()
        for seed in range(seeds)
    ]


def write(run_dir: Path, lines: list[dict]) -> Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "results.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    return run_dir


def report(run_dir: Path):
    return write_report(run_dir / "report", load_results(run_dir), ARMS, ORDER, ORDER)


def write_plan(run_dir: Path, n: int, version: int = 2) -> None:
    ids = [f"m/active/{SINGLE}/{1000 + k}/1" for k in range(n)]
    plan = ids if version == 1 else {"v": 2, "fields": {}, "episodes": ids}
    (run_dir / "plan.json").write_text(json.dumps(plan))


# -- the first lines --------------------------------------------------------------------------


@pytest.mark.parametrize("version", [1, 2])
def test_an_incomplete_sweep_says_so_before_any_number(tmp_path, version):
    lines = pattern("m", "active", 1, {SINGLE: 5}, seeds=15)  # 15 episodes, all successful
    run_dir = write(tmp_path, lines)
    write_plan(run_dir, 2160, version)
    out = report(run_dir)
    alert = "incomplete sweep: 15 of 2,160 planned episodes scored; every number below covers "
    assert out.summary[0].startswith(alert)
    md = (out.directory / "report.md").read_text()
    assert md.startswith(f"# VA-Bench report\n\n- **{alert}")
    page = (out.directory / "report.html").read_text()
    assert page.index("<p class='alert'>incomplete sweep: 15 of 2,160") < page.index("<ul>")


def test_a_finished_sweep_has_no_alert(tmp_path):
    run_dir = write(tmp_path, pattern("m", "active", 1, {SINGLE: 1}, seeds=3))
    write_plan(run_dir, 3)
    out = report(run_dir)
    assert not out.summary[0].startswith("incomplete")
    assert "class='alert'" not in (out.directory / "report.html").read_text()


def test_the_headline_reads_number_unit_runs(tmp_path):
    lines = pattern("a", "active", 1, {SINGLE: 4, OTHER: 1}) + pattern(
        "a", "active", 2, {SINGLE: 3, OTHER: 2}
    )
    lines += pattern("a", "passive", 1, {SINGLE: 0, OTHER: 0})
    summary = report(write(tmp_path, lines)).summary
    # active: run 1 (1 + 1/4)/2 = 62.50, run 2 (3/4 + 1/2)/2 = 62.50: SD 0
    assert "a / active: macro-average success 62.50 ± 0.00 % (mean ± SD over 2 runs)" in summary
    assert "a / passive: macro-average success 0.00 % (1 run)" in summary
    assert not any("(1 run) %" in s or "run(s)" in s for s in summary)


# -- learning stage ---------------------------------------------------------------------------


def write_session(run_dir: Path, model: str, family: str) -> None:
    """A learned summary as the sweep leaves it: <family>.json, and beside it the session's
    folder, whose result learning.json is the same session again (also in a set-aside
    attempt)."""
    from vabench.agent.learning import LearningResult, write_result

    result = LearningResult.model_validate(
        {
            "task": family,
            "model": model,
            "label": family,
            "n_frames": 40,
            "status": "learned",
            "stop_reason": "learned",
        }
    )
    summary = run_dir / "summaries" / model / f"{family}.json"
    summary.parent.mkdir(parents=True, exist_ok=True)
    write_result(summary, result)
    session = summary.parent / family
    (session / "attempt_1").mkdir(parents=True)
    shutil.copy(summary, session / "learning.json")
    shutil.copy(summary, session / "attempt_1" / "learning.json")


def test_each_learning_session_is_one_row(tmp_path):
    run_dir = write(tmp_path, pattern("m", "active", 1, {SINGLE: 1}))
    write_session(run_dir, "m", SINGLE)
    write_session(run_dir, "vendor/m", OTHER)  # a model name with a slash: folders in folders
    out = report(run_dir).directory
    with open(out / "learning_stage.csv") as f:
        rows = [(r["model"], r["family"]) for r in csv.DictReader(f)]
    assert rows == [("m", SINGLE), ("vendor/m", OTHER)]
    md = (out / "learning_stage.md").read_text()
    assert md.count(f"| m | {SINGLE} |") == 1 and md.count(f"| vendor/m | {OTHER} |") == 1


# -- figures ----------------------------------------------------------------------------------


@pytest.fixture
def drawn(monkeypatch):
    """The matplotlib figures the report draws, in order (their PNGs are made as before)."""
    made = []
    png = figures._png

    def keep(fig):
        made.append(fig)
        return png(fig)

    monkeypatch.setattr(figures, "_png", keep)
    return made


def legend_of(fig) -> list[tuple[str, tuple]]:
    (ax,) = fig.axes
    legend = ax.get_legend()
    if legend is None:
        return []
    return [
        (t.get_text(), tuple(h.get_facecolor()))
        for t, h in zip(legend.texts, legend.legend_handles, strict=True)
    ]


def test_the_macro_legend_stays_true_without_dual_arm_data(tmp_path, drawn):
    spreads = _spreads(pattern("m", "active", 1, {SINGLE: 2, OTHER: 1}))  # single-arm only
    figures.macro_figure(spreads)
    labels = legend_of(drawn[-1])
    assert [text for text, _ in labels] == ["Single-arm", "Dual-arm (no data)", "All"]
    colours = [colour for _, colour in labels]
    assert colours[1] != colours[0]  # matplotlib would give the empty series the first colour
    assert len(set(colours)) == 3


def test_the_macro_figure_without_scored_episodes_says_so(drawn):
    figures.macro_figure({})
    (ax,) = drawn[-1].axes
    assert [t.get_text() for t in ax.texts] == ["no scored episode yet"]
    assert legend_of(drawn[-1]) == []


def _spreads(lines: list[dict]):
    from vabench.report import stats
    from vabench.run_records import parse_record

    records: list[Record] = [parse_record(x, "test", i + 1) for i, x in enumerate(lines)]
    return stats.macro_spread(stats.macro_averages(stats.task_cells(records), ARMS))


# -- report.html ------------------------------------------------------------------------------


def test_the_page_has_margins_contents_and_figures_beside_their_tables(tmp_path):
    lines = pattern("m", "active", 1, {SINGLE: 3, DUAL: 1}) + pattern(
        "m", "passive", 1, {SINGLE: 1, DUAL: 1}
    )
    out = report(write(tmp_path, lines)).directory
    page = (out / "report.html").read_text()
    style = page[page.index("<style>") : page.index("</style>")]
    assert re.search(r"body \{[^}]*padding: [^;]*\dre?m", style)  # never text at the window edge
    toc = page[page.index("<nav class='toc'>") : page.index("</nav>")]
    sections = re.findall(r"<section id='(\w+)'>", page)
    assert sections[:5] == [
        "overall",
        "task_matrix",
        "macro_average",
        "success_per_task",
        "active_passive",
    ]
    assert re.findall(r"href='#(\w+)'", toc) == sections
    for table, figure in [
        ("Macro-average success (mean ± sample SD across runs)", "Macro-average success"),
        ("m — active", "m — active: per-task success"),
        ("m — passive", "m — passive: per-task success"),
        ("m — run 1", "m: active vs passive (run 1)"),
        (
            "Overall success per condition (%, mean ± sample SD across runs)",
            "Overall success per condition",
        ),
        (
            "Success per task and condition (%, mean ± sample SD across runs)",
            "Success per task and condition",
        ),
    ]:
        pair = re.search(
            rf"<div class='pair'><div class='table'><h3>{re.escape(table)}</h3>\n<table>.*?"
            rf"</table>\n</div><figure><img alt=\"{re.escape(figure)}\"",
            page,
        )
        assert pair, f"{figure!r} is not beside {table!r}"
    assert page.count('src="data:image/png;base64,') == 7  # 4 + overall, matrix, published
