"""vabench.report: loading, the paper's statistics on hand-made records, and the written report.

Expected values are worked out by hand in the comments (exact fractions), not taken from the
code under test.
"""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import pytest

from vabench.report import ReportError, load_results, make_report
from vabench.report import active_passive as AP
from vabench.report import stats as S
from vabench.report.__main__ import main
from vabench.run_records import Record, parse_record

CUBE, BELL, POT = "grasp_single_cube", "click_bell_right", "lift_pot"
ARMS = {CUBE: 1, BELL: 1, POT: 2}


def line(
    model: str,
    track: str,
    task: str,
    seed: int,
    run: int,
    success: bool,
    status: str | None = None,
    **fields,
) -> dict:
    status = status or ("success" if success else "failure")
    return {
        "v": 1,
        "track": track,
        "episode_dir": f"episodes/{model}/{track}/{task}/seed_{seed}/run_{run}",
        "task": task,
        "seed": seed,
        "model": model,
        "protocol": track,
        "run": run,
        "status": status,
        "success": success,
        "stop_reason": "success" if success else "budget_exhausted",
        "step_budget": 50,
        "n_checkpoints": fields.pop("n_checkpoints", 3),
        **fields,
    }


def pattern(model: str, track: str, run: int, successes: dict[str, int], seeds: int = 4):
    """`seeds` scored episodes per task, the first `successes[task]` of them successful."""
    return [
        line(model, track, task, seed, run, seed < k)
        for task, k in successes.items()
        for seed in range(seeds)
    ]


def write(run_dir: Path, lines: list[dict], tail: str = "") -> Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    text = "".join(json.dumps(x) + "\n" for x in lines) + tail
    (run_dir / "results.jsonl").write_text(text)
    return run_dir


def records(lines: list[dict]) -> list[Record]:
    return [parse_record(x, "test", i + 1) for i, x in enumerate(lines)]


# Three runs of model "m", active track, 4 seeds per task:
#   run 1: cube 4/4, bell 2/4, pot 0/4 -> single (1 + 1/2)/2 = 3/4, dual 0,   all 1/2
#   run 2: cube 3/4, bell 1/4, pot 1/4 -> single 1/2,                 dual 1/4, all 5/12
#   run 3: cube 2/4, bell 2/4, pot 2/4 -> single 1/2,                 dual 1/2, all 1/2
RUNS = {1: {CUBE: 4, BELL: 2, POT: 0}, 2: {CUBE: 3, BELL: 1, POT: 1}, 3: {CUBE: 2, BELL: 2, POT: 2}}


def three_runs() -> list[dict]:
    out = [x for run, k in RUNS.items() for x in pattern("m", "active", run, k)]
    # Unscored records must not count: a re-run infrastructure error of a scored episode, and
    # one that never got scored (bell would become 2/5 in run 1 if it counted).
    out.insert(0, line("m", "active", CUBE, 0, 1, False, status="infrastructure_error"))
    out.append(line("m", "active", BELL, 4, 1, False, status="infrastructure_error"))
    out.append(line("m", "active", BELL, 5, 1, False, status="error"))
    return out


def test_per_task_counts_ignore_unscored():
    cells = {(c.task, c.run): c for c in S.task_cells(records(three_runs()))}
    assert (cells[(CUBE, 1)].successes, cells[(CUBE, 1)].total) == (4, 4)
    assert (cells[(BELL, 1)].successes, cells[(BELL, 1)].total) == (2, 4)
    assert (cells[(POT, 2)].successes, cells[(POT, 2)].total) == (1, 4)
    assert len(cells) == 9


def test_macro_averages_and_sample_sd():
    macros = S.macro_averages(S.task_cells(records(three_runs())), ARMS)
    got = {(m.run, m.subset): m.rate for m in macros}
    assert got[(1, "single")] == Fraction(3, 4)
    assert got[(1, "dual")] == 0
    assert got[(1, "all")] == Fraction(1, 2)
    assert got[(2, "all")] == Fraction(5, 12)
    spread = S.macro_spread(macros)
    single = spread[("m", "active", "single")]
    # mean 7/12; deviations 1/6, -1/12, -1/12; squares sum 1/24; / (n - 1) = 1/48
    assert single.mean == Fraction(7, 12)
    assert single.variance == Fraction(1, 48)
    assert single.sd == pytest.approx(math.sqrt(1 / 48), rel=1e-15)
    dual = spread[("m", "active", "dual")]  # 0, 1/4, 1/2: mean 1/4, variance (1/16+1/16)/2
    assert (dual.mean, dual.variance, dual.sd) == (Fraction(1, 4), Fraction(1, 16), 0.25)
    everything = spread[("m", "active", "all")]  # 1/2, 5/12, 1/2: mean 17/36, var 1/432
    assert (everything.mean, everything.variance) == (Fraction(17, 36), Fraction(1, 432))


def test_macro_average_weights_families_not_episodes():
    # cube 1/1 and bell 1/3 (unequal totals): the macro-average is (1 + 1/3) / 2 = 2/3, while
    # pooling episodes would give 2/4.
    lines = [line("u", "active", CUBE, 0, 1, True)]
    lines += [line("u", "active", BELL, s, 1, s == 0) for s in range(3)]
    (single, dual, everything) = S.macro_averages(S.task_cells(records(lines)), ARMS)
    assert single.rate == Fraction(2, 3)
    assert dual.rate is None  # no dual-arm family ran
    assert everything.families == (BELL, CUBE)


def test_one_run_has_no_sd():
    spread = S.mean_sd([Fraction(1, 2)])
    assert (spread.mean, spread.sd, spread.variance) == (Fraction(1, 2), None, None)


def test_sign_test_values():
    assert AP.sign_test(0, 0) == 1
    assert AP.sign_test(1, 5) == Fraction(2 * (1 + 5), 32)
    assert AP.sign_test(4, 5) == Fraction(2 * (1 + 5), 32)
    assert AP.sign_test(3, 6) == 1  # 2 * 42/64 > 1 is capped
    assert AP.sign_test(0, 3) == Fraction(2, 8)


# tab:multiview-per-task (paper.tex): per-family successes out of 20 seeds, active / passive,
# first base-evaluation run, in the table's row order.
PAPER_FAMILIES = [
    "click_bell_right",
    "grasp_pen_leaning_cube",
    "grasp_single_bottle",
    "grasp_single_bottle_upright",
    "grasp_single_cube",
    "grasp_single_pen",
    "place_cube_in_bowl",
    "place_cube_on_cube",
    "place_single_bottle_upright",
    "place_single_cube",
    "beat_block_hammer_right",
    "place_shoe",
    "handover_horizontal_block",
    "lift_pot",
]
PAPER_COUNTS = {  # model: (active counts, passive counts)
    "Qwen3.8-max": (
        [16, 13, 19, 14, 19, 16, 17, 19, 9, 12, 0, 7, 0, 0],
        [19, 11, 12, 8, 7, 11, 1, 5, 0, 2, 1, 1, 0, 0],
    ),
    "GPT-5.6-sol": (
        [16, 5, 18, 16, 19, 7, 19, 20, 3, 17, 3, 14, 0, 0],
        [14, 2, 11, 13, 15, 6, 17, 14, 0, 0, 0, 3, 0, 0],
    ),
    "Opus-5": (
        [12, 8, 15, 12, 18, 16, 20, 16, 8, 18, 1, 8, 0, 0],
        [10, 6, 13, 7, 11, 13, 8, 6, 2, 6, 0, 3, 0, 0],
    ),
    "Doubao-2.1": (
        [0, 1, 17, 10, 3, 7, 0, 2, 1, 1, 0, 0, 0, 0],
        [3, 0, 7, 2, 0, 3, 0, 0, 0, 0, 0, 0, 0, 0],
    ),
}
# Text of the paper: passive worse on 10 of 12, 12 of 12, 12 of 12 and 8 of 9 non-tied
# families; two-sided sign tests p = 0.039, 0.0005, 0.0005, 0.039 (printed precision).
PAPER_SIGN = {
    "Qwen3.8-max": (10, 12, "0.039", 3),
    "GPT-5.6-sol": (12, 12, "0.0005", 4),
    "Opus-5": (12, 12, "0.0005", 4),
    "Doubao-2.1": (8, 9, "0.039", 3),
}
# tab:multiview-comparison totals (single-arm /220, all /280), to check the transcription.
PAPER_TOTALS = {
    "Qwen3.8-max": (154, 77, 161, 78),
    "GPT-5.6-sol": (143, 92, 157, 95),
    "Opus-5": (144, 82, 152, 85),
    "Doubao-2.1": (42, 15, 42, 15),
}


@pytest.mark.parametrize("model", list(PAPER_COUNTS))
def test_sign_test_reproduces_paper(model):
    active, passive = PAPER_COUNTS[model]
    assert (sum(active[:11]), sum(passive[:11]), sum(active), sum(passive)) == PAPER_TOTALS[model]
    cells = [
        S.Cell(model, track, task, 1, n, 20)
        for track, counts in (("active", active), ("passive", passive))
        for task, n in zip(PAPER_FAMILIES, counts, strict=True)
    ]
    (cmp,) = AP.track_comparisons(cells)
    worse, non_tied, printed, digits = PAPER_SIGN[model]
    assert (cmp.passive_worse, cmp.non_tied, cmp.runs) == (worse, non_tied, (1,))
    assert f"{round(float(cmp.p_value), digits):.{digits}f}".rstrip("0") == printed.rstrip("0")
    if model == "Qwen3.8-max":  # 2 * (C(12,0) + C(12,1) + C(12,2)) / 2^12
        assert cmp.p_value == Fraction(2 * 79, 4096)


def test_active_passive_pairs_matched_runs_and_pools():
    lines = three_runs()
    # passive runs 1 and 2 only; run 1: cube 1/4 (worse by 3), bell 2/4 (tie), pot 1/4 (better)
    lines += pattern("m", "passive", 1, {CUBE: 1, BELL: 2, POT: 1})
    # run 2: cube 0/4 (worse), bell 0/4 (worse), pot 0/4 (worse)
    lines += pattern("m", "passive", 2, {CUBE: 0, BELL: 0, POT: 0})
    comparisons = AP.track_comparisons(S.task_cells(records(lines)))
    assert [c.runs for c in comparisons] == [(1,), (2,), (1, 2)]
    run1, run2, pooled = comparisons
    pairs = {p.task: p for p in run1.families}
    assert (pairs[CUBE].active, pairs[CUBE].passive, pairs[CUBE].delta) == (4, 1, Fraction(-3, 4))
    assert (run1.passive_worse, run1.passive_better, run1.ties) == (1, 1, 1)
    assert run1.p_value == 1  # 2 * P[X <= 1], n = 2: 2 * 3/4 capped
    assert (run2.passive_worse, run2.non_tied, run2.p_value) == (3, 3, Fraction(2, 8))
    # pooled: cube 7/8 vs 1/8, bell 3/8 vs 2/8, pot 1/8 vs 1/8 (tie)
    pooled_pairs = {p.task: (p.active, p.active_total, p.passive) for p in pooled.families}
    assert pooled_pairs == {CUBE: (7, 8, 1), BELL: (3, 8, 2), POT: (1, 8, 1)}
    assert (pooled.passive_worse, pooled.ties, pooled.p_value) == (2, 1, Fraction(2, 4))


def test_checkpoint_micro_average():
    lines = [
        line("c", "active", CUBE, 0, 1, True, progress=3, n_checkpoints=3),
        line("c", "active", CUBE, 1, 1, False, progress=1, n_checkpoints=3),
        line("c", "active", POT, 0, 1, False, progress=2, n_checkpoints=4),
        line("c", "active", POT, 1, 1, False, "infrastructure_error", progress=4, n_checkpoints=4),
    ]
    got = {c.subset: (c.reached, c.possible) for c in S.checkpoint_micro(records(lines), ARMS)}
    assert got == {"single": (4, 6), "dual": (2, 4), "all": (6, 10)}


def test_usage_over_scored_episodes():
    tokens_a = {"input": 100, "output": 10}
    tokens_b = {"input": 300, "output": 30, "reasoning": 5}
    lines = [
        line("x", "active", CUBE, 0, 1, True, steps_used=10, camera_actions=5, robot_actions=5,
             invalid_actions=1, model_calls=12, invalid_outputs=1, tokens=tokens_a, cost_usd=0.5),
        line("x", "active", CUBE, 1, 1, False, steps_used=30, camera_actions=5, robot_actions=25,
             invalid_actions=2, model_calls=8, invalid_outputs=1, tokens=tokens_b, cost_usd=1.5),
        line("x", "active", CUBE, 2, 1, False, "infrastructure_error", steps_used=50,
             camera_actions=50, model_calls=99, cost_usd=7.0),
    ]  # fmt: skip
    (u,) = S.usage(records(lines))
    assert (u.episodes, u.mean_steps, u.camera_share) == (2, 20.0, 0.25)
    assert (u.invalid_output_share, u.invalid_action_share) == (0.1, 0.1)
    assert u.tokens == {"input": 400, "cached_input": 0, "cache_write": 0, "output": 40,
                        "reasoning": 5}  # fmt: skip
    assert (u.total_tokens, u.cost_usd) == (445, 2.0)
    assert S.unscored_counts(records(lines)) == {("x", "active", "infrastructure_error"): (1, 7.0)}


# -- loading ------------------------------------------------------------------------------------


def test_truncated_last_line_is_tolerated(tmp_path):
    lines = pattern("m", "active", 1, {CUBE: 1}, seeds=2)
    run_dir = write(tmp_path, lines, tail='{"v": 1, "track": "act')
    results = load_results(run_dir)
    assert results.truncated_tail and len(results.scored) == 2


def test_complete_last_line_without_newline_is_read(tmp_path):
    lines = pattern("m", "active", 1, {CUBE: 1}, seeds=2)
    run_dir = write(tmp_path, lines[:1], tail=json.dumps(lines[1]))
    results = load_results(run_dir)
    assert not results.truncated_tail and len(results.scored) == 2


def test_malformed_line_elsewhere_names_file_and_line(tmp_path):
    lines = pattern("m", "active", 1, {CUBE: 1}, seeds=2)
    text = json.dumps(lines[0]) + "\n{not json\n" + json.dumps(lines[1]) + "\n"
    (tmp_path / "results.jsonl").write_text(text)
    with pytest.raises(ReportError, match=r"results\.jsonl:2: not valid JSON"):
        load_results(tmp_path)


def test_malformed_terminated_last_line_is_an_error(tmp_path):
    # a line ending in a newline was written whole: garbage there is not a crash artefact
    run_dir = write(tmp_path, pattern("m", "active", 1, {CUBE: 1}, seeds=1), tail="{oops\n")
    with pytest.raises(ReportError, match=r"results\.jsonl:2"):
        load_results(run_dir)


def test_invalid_field_is_named(tmp_path):
    bad = line("m", "active", CUBE, 0, 1, True)
    bad["seed"] = "zero"
    with pytest.raises(ReportError, match=r"results\.jsonl:1: field 'seed'"):
        load_results(write(tmp_path, [bad]))


def test_success_contradicting_status_is_rejected(tmp_path):
    bad = line("m", "active", CUBE, 0, 1, True)
    bad["status"] = "failure"
    with pytest.raises(ReportError, match="field 'success'"):
        load_results(write(tmp_path, [bad]))


def test_duplicate_scored_record_is_rejected(tmp_path):
    lines = pattern("m", "active", 1, {CUBE: 1}, seeds=2)
    lines.append(line("m", "active", CUBE, 1, 1, True))
    with pytest.raises(ReportError, match=r"results\.jsonl:3: duplicate .* first is at line 2"):
        load_results(write(tmp_path, lines))


def test_same_episode_in_another_run_or_track_is_no_duplicate(tmp_path):
    lines = [
        line("m", "active", CUBE, 0, 1, True),
        line("m", "active", CUBE, 0, 2, True),
        line("m", "passive", CUBE, 0, 1, True),
        line("m", "active", CUBE, 0, 1, False, status="infrastructure_error"),
        line("m", "active", CUBE, 0, 1, False, status="infrastructure_error"),
    ]
    results = load_results(write(tmp_path, lines))
    assert (len(results.scored), len(results.unscored)) == (3, 2)


def test_missing_or_empty_results(tmp_path):
    with pytest.raises(ReportError, match="not found"):
        load_results(tmp_path)
    (tmp_path / "results.jsonl").write_text("")
    with pytest.raises(ReportError, match="no records"):
        load_results(tmp_path)


def test_unknown_task_is_named():
    with pytest.raises(ReportError, match="unknown task 'nope'"):
        S.subset_of("nope", ARMS)


# -- the written report -------------------------------------------------------------------------


def full_sweep() -> list[dict]:
    """2 models x 2 tracks x 3 tasks x 4 seeds x (3 active, 2 passive) runs."""
    out = []
    for model, shift in (("model-a", 0), ("vendor/model b", 1)):
        for run, k in RUNS.items():
            out += pattern(model, "active", run, {t: max(0, n - shift) for t, n in k.items()})
        for run in (1, 2):
            out += pattern(model, "passive", run, {CUBE: 1, BELL: run, POT: 0})
    out.append(line("model-a", "active", BELL, 9, 1, False, status="infrastructure_error"))
    return out


def test_cli_writes_every_file(tmp_path, capsys):
    run_dir = write(tmp_path / "run", full_sweep())
    assert main([str(run_dir)]) == 0
    printed = capsys.readouterr().out
    report = run_dir / "report"
    assert str(report) in printed and "sign test" in printed
    for name in ("report.md", "report.html", "macro_average.md", "success_per_task.md",
                 "active_passive.md", "usage.md", "checkpoints.md", "macro_average.csv",
                 "macro_average_runs.csv", "success_per_task.csv", "active_passive.csv",
                 "sign_test.csv", "usage.csv", "checkpoints.csv", "unscored.csv"):  # fmt: skip
        assert (report / name).stat().st_size > 0, name
    pngs = sorted((report / "figures").glob("*.png"))
    # 1 macro-average + 4 per-task (2 models x 2 tracks) + 2 active-vs-passive, and the
    # publication's overall bars, task matrix and its published reference (no annotations: no
    # radar)
    assert len(pngs) == 10
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)
    page = (report / "report.html").read_text()
    assert page.count('src="data:image/png;base64,') == 10
    assert "figures/" not in page and "http" not in page  # nothing outside the file
    assert not list(report.rglob("*.tmp"))
    # the CSV carries the statistics: model-a active, all families: mean 17/36 (see RUNS)
    with open(report / "macro_average.csv") as f:
        rows = {(r["model"], r["track"], r["subset"]): r for r in csv.DictReader(f)}
    row = rows[("model-a", "active", "all")]
    assert float(row["mean"]) == pytest.approx(17 / 36, rel=1e-12)
    assert float(row["sd"]) == pytest.approx(math.sqrt(1 / 432), rel=1e-12)
    # the registry's classification reached the report: 11 single-arm + 3 dual-arm families,
    # and the run's missing base families are named
    md = (report / "report.md").read_text()
    assert "11 single-arm, 3 dual-arm" in md and "lacks 11 of 14 base families" in md


def test_infrastructure_retries_are_counted_not_scored(tmp_path):
    run_dir = write(tmp_path, pattern("m", "active", 1, {CUBE: 1}, seeds=2))
    retry = line("m", "active", CUBE, 0, 1, False, status="infrastructure_error")
    (run_dir / "infrastructure.jsonl").write_text(json.dumps(retry) + "\n" + '{"mod')
    results = load_results(run_dir)
    assert results.retried == {("m", "active"): 1}
    assert (len(results.scored), len(results.unscored)) == (2, 0)


def test_make_report_returns_directory_and_replaces_stale_figures(tmp_path):
    run_dir = write(tmp_path / "run", full_sweep())
    stale = run_dir / "report" / "figures" / "success_gone_active.png"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"old")
    assert make_report(run_dir) == run_dir / "report"
    assert not stale.exists()


def test_cli_missing_results_is_one_clear_error(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "vabench.report", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"error: {tmp_path / 'results.jsonl'}: not found " + (
        f"(is {tmp_path} a sweep run directory?)"
    )


# -- skipped episodes ------------------------------------------------------------------------


def skipped(model: str, track: str, task: str, seed: int, run: int) -> dict:
    """An episode the model stopped before its first step (nothing attempted)."""
    return line(model, track, task, seed, run, False, stop_reason="model_stop", steps_used=0)


def test_all_skipped_family_is_left_out_of_the_sign_test(tmp_path):
    # active run 1: cube 4/4, bell 2/4, pot 0/4 (all four skipped: stopped at once)
    # passive run 1: cube 1/4 (worse), bell 2/4 (tie), pot 0/4 attempted (budget exhausted)
    lines = pattern("m", "active", 1, {CUBE: 4, BELL: 2})
    lines += [skipped("m", "active", POT, seed, 1) for seed in range(4)]
    lines += pattern("m", "passive", 1, {CUBE: 1, BELL: 2, POT: 0})
    (cmp,) = AP.track_comparisons(S.task_cells(records(lines)))
    pairs = {p.task: p for p in cmp.families}
    assert (pairs[POT].active_skipped, pairs[POT].skipped_side) == (4, "active")
    assert pairs[CUBE].skipped_side is None and pairs[BELL].skipped_side is None
    # the pot pair is a tie in counts (0/4 vs 0/4) but compares nothing: not a tie, left out
    assert (cmp.passive_worse, cmp.passive_better, cmp.ties, cmp.skipped) == (1, 0, 1, (POT,))
    assert (cmp.compared, cmp.p_value) == (2, 1)  # n = 1, k = 1: 2 * 1/2
    # an attempted family with some skipped episodes stays in
    part = [x for x in lines if x["task"] != POT or x["track"] == "passive"]
    part += [skipped("m", "active", POT, 0, 1)] + pattern("m", "active", 1, {POT: 0})[1:]
    (cmp2,) = AP.track_comparisons(S.task_cells(records(part)))
    assert (cmp2.skipped, cmp2.ties) == ((), 2)

    out = make_report(write(tmp_path, lines))
    md = (out / "report.md").read_text()
    assert f"| {POT} | 0/4 | 0/4 | — (all skipped under active) |" in md
    assert "left out of the sign test and shown without a Δ, every episode skipped" in md
    with open(out / "active_passive.csv") as f:
        rows = {r["task"]: r for r in csv.DictReader(f)}
    assert (rows[POT]["delta_rate"], rows[POT]["active_skipped"]) == ("", "4")


def test_no_sign_test_when_every_family_is_skipped(tmp_path):
    lines = pattern("m", "active", 1, {CUBE: 3})
    lines += [skipped("m", "passive", CUBE, seed, 1) for seed in range(4)]
    (cmp,) = AP.track_comparisons(S.task_cells(records(lines)))
    assert (cmp.skipped, cmp.p_value, cmp.non_tied) == ((CUBE,), None, 0)
    out = make_report(write(tmp_path, lines))
    md = (out / "report.md").read_text()
    assert "| m | run 1 | 1 | 0 | 0 | 0 | 0 | — |" in md
    assert "no family is left: no sign test" in md
    head = md.split("\n## ")[0]  # the summary lines above the sections
    assert "no sign test, every family was skipped (stopped before its first step)" in head
    assert "sign test p = " not in head
