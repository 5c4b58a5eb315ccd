"""vabench.report's track sections (summary source, learning stage, controlled transfer, long
horizon) on hand-made records and hand-made task metadata.

Expected values are worked out by hand in the comments (exact fractions), not taken from the
code under test. Task names are made up: arms and suites come from the injected maps.
"""

from __future__ import annotations

import csv
import json
import math
from fractions import Fraction
from pathlib import Path

import pytest

from vabench.report import ReportError, load_results
from vabench.report.build import write_report
from vabench.report.conditions import TaskMeta, condition_cells
from vabench.report.suites import long_horizon, transfer_comparisons
from vabench.report.summaries import SummaryComparison, cross_model, summary_comparisons
from vabench.run_records import Record, parse_record

A1, A2, D, X = "task_a1", "task_a2", "task_dual", "task_x"
B1, B2, B3, H1, H2, H3 = "base_1", "base_2", "base_3", "base_1_heldout", "base_2_heldout", "h3"
L = "basket"
ARMS = {A1: 1, A2: 1, D: 2, X: 1, B1: 1, B2: 1, B3: 1, H1: 1, H2: 1, H3: 1, L: 2}
ORDER = [A1, A2, D, X, B1, B2, B3, H1, H2, H3, L]
BASE = (A1, A2, D, X, B1, B2, B3)
META = TaskMeta(
    suite={
        **dict.fromkeys(BASE, "base"),
        H1: "transfer",
        H2: "transfer",
        H3: "transfer",
        L: "long_horizon",
    },
    base_family={H1: B1, H2: B2, H3: B3},
)
NEW_HEADINGS = (
    "Summary source",
    "Learning stage",
    "Controlled transfer",
    "Long-horizon composition",
)


def line(model, track, task, seed, run, success, protocol="active", mode="own", **fields) -> dict:
    source = {"own": model, "none": None}.get(mode, mode.removeprefix("shared:"))
    return {
        "v": 1,
        "track": track,
        "episode_dir": f"episodes/{model}/{track}/{task}/seed_{seed}/run_{run}",
        "task": task,
        "seed": seed,
        "model": model,
        "protocol": protocol,
        "run": run,
        "status": "success" if success else "failure",
        "success": success,
        "stop_reason": "success" if success else "budget_exhausted",
        "step_budget": 50,
        "n_checkpoints": fields.pop("n_checkpoints", 3),
        "summary_mode": mode,
        "summary_from": source,
        "summary_status": "none" if source is None else "learned",
        **fields,
    }


def pattern(model, track, run, successes, mode="own", protocol="active", seeds=4) -> list[dict]:
    """`seeds` episodes per task, the first `successes[task]` of them successful."""
    return [
        line(model, track, task, seed, run, seed < k, protocol, mode)
        for task, k in successes.items()
        for seed in range(seeds)
    ]


def records(lines: list[dict]) -> list[Record]:
    return [parse_record(x, "test", i + 1) for i, x in enumerate(lines)]


def write(run_dir: Path, lines: list[dict]) -> Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "results.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    return run_dir


def report(run_dir: Path, meta: TaskMeta | None = META) -> Path:
    write_report(run_dir / "report", load_results(run_dir), ARMS, ORDER, BASE, meta)
    return run_dir / "report"


def read_csv(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


# -- summary source ------------------------------------------------------------------------------


# Reader "r", protocol active, 4 seeds per task:
#   own       run 1: A1 4, A2 2, D 0, X 4   run 2: A1 2, A2 2, D 2, X 0
#   shared:w  run 1: A1 2, A2 0, D 0        run 2: A1 2, A2 2, D 0
#   none      run 1: A1 0, A2 0, D 4
# Matched tasks {A1, A2, D} (X is run under own only); matched runs {1} (none ran run 1 only).
# own macros: run 1 single (1 + 1/2)/2 = 3/4, dual 0, all 1/2; run 2 single 1/2, dual 1/2, all 1/2
#   -> single 5/8 (variance 1/32), dual 1/4 (variance 1/8), all 1/2 (variance 0)
# shared:w: run 1 single 1/4, dual 0, all 1/6; run 2 single 1/2, dual 0, all 1/3
#   -> single 3/8, dual 0, all 1/4; minus own: -1/4, -1/4, -1/4
# none: one run: single 0, dual 1, all 1/3; minus own: -5/8, +3/4, -1/6
# Pooled over run 1 and the matched tasks: own 6/12 = 1/2, shared:w 2/12 = 1/6 (Δ -1/3).
# Author "w": own 9/12 = 3/4, shared:w (its own summary again) 12/12 = 1 (Δ +1/4).
# "q": own 3/12 = 1/4, shared:w 6/12 = 1/2 (Δ +1/4).
# avg: own (1/4 + 1/2 + 3/4)/3 = 1/2; rate (1/2 + 1/6 + 1)/3 = 5/9;
#   Δ without the author (q +1/4, r -1/3) = -1/24 (with it: 1/18).
def summary_sweep() -> list[dict]:
    out = []
    out += pattern("r", "active", 1, {A1: 4, A2: 2, D: 0, X: 4})
    out += pattern("r", "active", 2, {A1: 2, A2: 2, D: 2, X: 0})
    out += pattern("r", "active_shared", 1, {A1: 2, A2: 0, D: 0}, "shared:w")
    out += pattern("r", "active_shared", 2, {A1: 2, A2: 2, D: 0}, "shared:w")
    out += pattern("r", "active_none", 1, {A1: 0, A2: 0, D: 4}, "none")
    out += pattern("w", "active", 1, {A1: 3, A2: 3, D: 3})
    out += pattern("w", "active_shared", 1, {A1: 4, A2: 4, D: 4}, "shared:w")
    out += pattern("q", "active", 1, {A1: 1, A2: 1, D: 1})
    out += pattern("q", "active_shared", 1, {A1: 2, A2: 2, D: 2}, "shared:w")
    # q's seeds 4-5 of A1 under shared:w ran without w's summary (its learning failed): still
    # counted under shared:w (run 2, outside the matched runs: no number above changes), noted
    failed = {"summary_status": "failed", "summary_from": None}
    out += [line("q", "active_shared", A1, s, 2, False, mode="shared:w", **failed) for s in (4, 5)]
    # one mode only (own, under both protocols): no summary comparison
    out += pattern("solo", "active", 1, {A1: 1})
    out += pattern("solo", "passive", 1, {A1: 2}, protocol="passive")
    return out


def comparisons() -> dict[str, SummaryComparison]:
    cells, notes = condition_cells(records(summary_sweep()))
    assert notes == []
    found, notes = summary_comparisons(cells, ARMS)
    assert notes == []
    return {c.model: c for c in found}


def test_summary_source_ablation_over_matched_tasks():
    by = comparisons()
    assert sorted(by) == ["q", "r", "w"]  # "solo" ran under one mode only
    r = by["r"]
    assert r.modes == ("own", "shared:w", "none")
    assert (r.tasks, r.left_out, r.runs) == ((A1, A2, D), (X,), (1,))
    own = {s: r.macros[("own", s)] for s in ("single", "dual", "all")}
    assert (own["single"].mean, own["single"].variance) == (Fraction(5, 8), Fraction(1, 32))
    assert (own["dual"].mean, own["dual"].variance) == (Fraction(1, 4), Fraction(1, 8))
    assert (own["all"].mean, own["all"].variance) == (Fraction(1, 2), 0)
    assert r.macros[("shared:w", "all")].values == (Fraction(1, 6), Fraction(1, 3))
    assert r.macros[("none", "all")].sd is None
    assert [r.delta("shared:w", s) for s in ("single", "dual", "all")] == [Fraction(-1, 4)] * 3
    assert [r.delta("none", s) for s in ("single", "dual", "all")] == [
        Fraction(-5, 8),
        Fraction(3, 4),
        Fraction(-1, 6),
    ]
    assert (r.pooled("own"), r.pooled("shared:w"), r.pooled("none")) == (
        Fraction(1, 2),
        Fraction(1, 6),
        Fraction(1, 3),
    )
    assert r.counts[("own", A1)] == (4, 4) and ("own", X) not in r.counts


def test_cross_model_avg_row_leaves_out_the_author():
    (cm,) = cross_model(list(comparisons().values()))
    assert (cm.protocol, cm.sources) == ("active", ("w",))
    rows = {row.model: row for row in cm.rows}
    assert rows["r"].delta("w") == Fraction(-1, 3)
    assert rows["w"].delta("w") == Fraction(1, 4)
    assert rows["q"].delta("w") == Fraction(1, 4)
    assert cm.avg_own == Fraction(1, 2)
    assert cm.avg_rate("w") == Fraction(5, 9)
    assert cm.avg_delta("w") == Fraction(-1, 24)


def test_same_condition_under_two_tracks_counts_once():
    lines = pattern("m", "active", 1, {A1: 4}) + pattern("m", "active_copy", 1, {A1: 0})
    cells, notes = condition_cells(records(lines))
    assert [(c.track, c.successes, c.total) for c in cells] == [("active", 4, 4)]
    assert notes == [
        f"m / active / summaries own / {A1}: run by tracks ['active', 'active_copy'] alike; "
        "only 'active' is counted"
    ]


def test_summary_modes_are_compared_within_a_suite():
    # base tasks under own and none; the held-out task under own (transfer track) and
    # shared:w: two comparisons, neither listing the other suite's tasks as left out
    lines = pattern("m", "active", 1, {A1: 2}) + pattern("m", "active_none", 1, {A1: 1}, "none")
    lines += pattern("m", "transfer", 1, {H1: 1}) + pattern("m", "t_w", 1, {H1: 3}, "shared:w")
    cells, _ = condition_cells(records(lines))
    found, notes = summary_comparisons(cells, ARMS, META.suite)
    got = [(c.suite, c.modes, c.tasks, c.left_out) for c in found]
    assert got == [
        ("base", ("own", "none"), (A1,), ()),
        ("transfer", ("own", "shared:w"), (H1,), ()),
    ]
    (cm,) = [c for c in cross_model(found)]
    assert (cm.suite, cm.rows[0].delta("w")) == ("transfer", Fraction(1, 2))
    assert notes == []


def test_modes_without_a_common_task_are_noted():
    lines = pattern("m", "active", 1, {A1: 1}) + pattern("m", "active_none", 1, {A2: 1}, "none")
    cells, _ = condition_cells(records(lines))
    found, notes = summary_comparisons(cells, ARMS)
    assert found == [] and notes == ["m / active: summary modes ['own', 'none'] share no task"]


def test_summary_source_section_written(tmp_path):
    out = report(write(tmp_path, summary_sweep()))
    md = (out / "report.md").read_text()
    assert "## Summary source" in md and (out / "summary_source.md").is_file()
    for heading in ("Learning stage", "Controlled transfer", "Long-horizon composition"):
        assert f"## {heading}" not in md
    assert "### r — active: summary source over 3 matched tasks (2 single-arm, 1 dual-arm)" in md
    assert "| w (shared) − own |  | -25.00 | -25.00 | -25.00 |" in md
    assert "| none (no summary) − own |  | -62.50 | +75.00 | -16.67 |" in md
    assert "| r | 50.00 | 16.67 | -33.33 |" in md
    assert "| avg | 50.00 | 55.56 | -4.17 |" in md
    assert f"| {A1} | 100.00 (4/4) | 50.00 (2/4) | 0.00 (0/4) |" in md
    assert f"left out, not run under every summary mode: ['{X}']" in md
    assert "solo — active: summary source" not in md
    assert "q / active_shared: 2 episode(s) ran without a summary (w's learning failed)" in md
    rows = read_csv(out / "summary_cross_model.csv")
    avg = next(x for x in rows if x["evaluated_model"] == "avg")
    assert float(avg["delta"]) == pytest.approx(-1 / 24, rel=1e-12)
    abl = read_csv(out / "summary_source.csv")
    own_single = next(
        x for x in abl if (x["model"], x["mode"], x["subset"]) == ("r", "own", "single")
    )
    assert float(own_single["sd"]) == pytest.approx(math.sqrt(1 / 32), rel=1e-12)
    assert len(read_csv(out / "summary_per_task.csv")) == 3 * 3 + 3 * 2 + 3 * 2
    page = (out / "report.html").read_text()
    assert "<h2>Summary source</h2>" in page


# -- learning stage ------------------------------------------------------------------------------


def write_learning(run_dir: Path, model: str, family: str, **fields) -> Path:
    from vabench.agent.learning import LearningResult, write_result

    path = run_dir / "summaries" / model / f"{family}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    result = {"task": family, "model": model, "label": family, "n_frames": 40, **fields}
    write_result(path, LearningResult.model_validate(result))
    return path


def test_learning_stage_table(tmp_path):
    run_dir = write(tmp_path, pattern("vendor/m", "active", 1, {A1: 1}))
    write_learning(
        run_dir, "vendor/m", A1, status="learned", stop_reason="learned", model_calls=3,
        frames_inspected=[0, 10, 20], learn_refusals=1,
    )  # fmt: skip
    write_learning(run_dir, "vendor/m", A2, status="failed", stop_reason="budget_exhausted")
    out = report(run_dir)
    md = (out / "report.md").read_text()
    assert "## Learning stage" in md and "## Summary source" not in md
    assert f"| vendor/m | {A1} | learned | learned | 3 | 3/40 | 1 |" in md
    assert f"| vendor/m | {A2} | failed | budget_exhausted | 0 | 0/40 | 0 |" in md
    assert [r["family"] for r in read_csv(out / "learning_stage.csv")] == [A1, A2]


def test_learning_stage_bad_file_names_file_and_field(tmp_path):
    run_dir = write(tmp_path, pattern("m", "active", 1, {A1: 1}))
    path = write_learning(run_dir, "m", A1, status="learned", stop_reason="learned")
    obj = json.loads(path.read_text())
    obj["model_calls"] = "many"
    path.write_text(json.dumps(obj))
    with pytest.raises(ReportError, match=rf"{path}: field 'model_calls'"):
        report(run_dir)
    path.write_text("{")
    with pytest.raises(ReportError, match=rf"{path}: not valid JSON"):
        report(run_dir)


# -- controlled transfer -------------------------------------------------------------------------


# Model m, protocol active, own summaries, 4 seeds:
#   base (track active)     run 1: B1 4, B2 2        run 2: B1 2, B2 2
#   held-out (transfer)     run 1: H1 2, H2 0, H3 4  run 2: H1 2, H2 2
# H3's base B3 never ran: left out. Run 1: base (1 + 1/2)/2 = 3/4, held-out (1/2 + 0)/2 = 1/4,
# Δ -1/2; run 2: base 1/2, held-out 1/2, Δ 0. Mean base 5/8, held-out 3/8, Δ -1/4 with
# variance ((1/4)^2 + (1/4)^2)/1 = 1/8. Per family pooled: B1 6/8 -> H1 4/8 (Δ -1/4),
# B2 4/8 -> H2 2/8 (Δ -1/4).
def transfer_sweep() -> list[dict]:
    out = []
    out += pattern("m", "active", 1, {B1: 4, B2: 2})
    out += pattern("m", "active", 2, {B1: 2, B2: 2})
    out += pattern("m", "transfer", 1, {H1: 2, H2: 0, H3: 4})
    out += pattern("m", "transfer", 2, {H1: 2, H2: 2})
    return out


def test_transfer_pairs_held_out_with_base_family():
    cells, _ = condition_cells(records(transfer_sweep()))
    (cmp,) = transfer_comparisons(cells, META)
    assert (cmp.model, cmp.protocol, cmp.mode, cmp.runs) == ("m", "active", "own", (1, 2))
    assert cmp.unmatched == (H3,)
    fams = {f.heldout: f for f in cmp.families}
    assert sorted(fams) == [H1, H2]
    assert (fams[H1].base, fams[H1].base_successes, fams[H1].base_total) == (B1, 6, 8)
    assert (fams[H1].heldout_successes, fams[H1].heldout_total) == (4, 8)
    assert fams[H1].delta == fams[H2].delta == Fraction(-1, 4)
    assert cmp.base.values == (Fraction(3, 4), Fraction(1, 2))
    assert cmp.heldout.mean == Fraction(3, 8)
    assert (cmp.delta.mean, cmp.delta.variance) == (Fraction(-1, 4), Fraction(1, 8))
    # the same records have one summary mode per protocol: no summary-source comparison
    assert summary_comparisons(cells, ARMS) == ([], [])


def test_transfer_base_falls_back_to_own_summary_runs():
    lines = pattern("m", "active", 1, {B1: 2}) + pattern("m", "t_none", 1, {H1: 1}, "none")
    cells, _ = condition_cells(records(lines))
    (cmp,) = transfer_comparisons(cells, META)
    (fam,) = cmp.families
    assert (cmp.mode, fam.base_mode, fam.delta) == ("none", "own", Fraction(-1, 4))


def test_transfer_task_without_base_family_is_named():
    cells, _ = condition_cells(records(pattern("m", "transfer", 1, {H1: 1})))
    meta = TaskMeta(suite=META.suite, base_family={})
    with pytest.raises(ReportError, match=f"task '{H1}': .*field 'base_family'"):
        transfer_comparisons(cells, meta)


def test_transfer_section_written(tmp_path):
    out = report(write(tmp_path, transfer_sweep()))
    md = (out / "report.md").read_text()
    assert "## Controlled transfer" in md and "## Summary source" not in md
    sd = f"{100 * math.sqrt(1 / 8):.2f}"
    assert f"| m | active | own | 2 | 1,2 | 62.50 ± 17.68 | 37.50 ± 17.68 | -25.00 ± {sd} |" in md
    assert f"| {B1} | {H1} | 75.00 (6/8) | 50.00 (4/8) | -25.00 |" in md
    assert f"left out, no base-family run under the same protocol and run: ['{H3}']" in md
    rows = read_csv(out / "transfer.csv")
    assert [(r["heldout_task"], float(r["delta_rate"])) for r in rows] == [(H1, -0.25), (H2, -0.25)]
    # without task metadata (no registry) there is no transfer section
    assert "Controlled transfer" not in (report(tmp_path, meta=None) / "report.md").read_text()


# -- long horizon --------------------------------------------------------------------------------


# Model m, track long_horizon, 5 checkpoints, 4 episodes per run:
#   run 1 progress 5, 2, 0, 3 (the 5 a strict success): placed 10/20, success 1/4
#   run 2 progress 1, 1, 0, 0: placed 2/20, success 0/4
# mean placed (1/2 + 1/10)/2 = 3/10, mean success 1/8.
def long_sweep() -> list[dict]:
    progress = {1: [5, 2, 0, 3], 2: [1, 1, 0, 0]}
    return [
        line("m", "long_horizon", L, seed, run, p == 5, progress=p, n_checkpoints=5)
        for run, ps in progress.items()
        for seed, p in enumerate(ps)
    ]


def test_long_horizon_objects_and_strict_success(tmp_path):
    (lh,) = long_horizon(records(long_sweep()), META)
    assert [(r.run, r.placed, r.possible, r.successes, r.episodes) for r in lh.runs] == [
        (1, 10, 20, 1, 4),
        (2, 2, 20, 0, 4),
    ]
    assert (lh.placed.mean, lh.success.mean) == (Fraction(3, 10), Fraction(1, 8))
    out = report(write(tmp_path, long_sweep()))
    md = (out / "report.md").read_text()
    assert "## Long-horizon composition" in md
    assert f"| m | long_horizon | {L} | 1 | 10/20 | 50.00 | 1/4 | 25.00 |" in md
    mean_row = f"| m | long_horizon | {L} | mean | 12/40 in all | 30.00 ± 28.28 | 1/8 in all |"
    assert mean_row + " 12.50 ± 17.68 |" in md
    assert len(read_csv(out / "long_horizon.csv")) == 2


# -- a base sweep's report is unchanged ----------------------------------------------------------


def base_sweep() -> list[dict]:
    """One model, active (2 runs) and passive (1 run), own summaries, as a base sweep records."""
    out = pattern("a", "active", 1, {A1: 4, A2: 1, D: 0})
    out += pattern("a", "active", 2, {A1: 3, A2: 2, D: 1})
    out += pattern("a", "passive", 1, {A1: 1, A2: 0, D: 0}, protocol="passive")
    return out


# report.md of base_sweep() written by the code before the track sections (commit 7a84126's
# vabench/report, the parent of 4ce55dd), with the results path replaced by {RESULTS}, and
# the headline's macro-averages worded "number unit (runs)".
BASE_REPORT_MD = """\
# VA-Bench report

- 36 scored episodes, 0 unscored records (0 episodes never scored) in {RESULTS}
- a / active: macro-average success 45.83 ± 5.89 % (mean ± SD over 2 runs)
- a / passive: macro-average success 8.33 % (1 run)
- a active vs passive (run 1): passive worse on 2 of 2 non-tied families, sign test p = 0.5

## Macro-average success

- base families (vabench.tasks): 6 single-arm, 1 dual-arm (dual-arm = the task uses more than one arm)
- lacks 4 of 7 base families ['task_x', 'base_1', 'base_2', 'base_3']: a / active run 1,2; a / passive run 1

### Macro-average success (mean ± sample SD across runs)

| model | track | runs | Single-arm % | Dual-arm % | All % |
|---|---|---|---|---|---|
| a | active | 2 | 62.50 ± 0.00 | 12.50 ± 17.68 | 45.83 ± 5.89 |
| a | passive | 1 | 12.50 (1 run) | 0.00 (1 run) | 8.33 (1 run) |

### Run-level macro-averages

| model | track | run | Single-arm % | Dual-arm % | All % | families (single+dual) |
|---|---|---|---|---|---|---|
| a | active | 1 | 62.50 | 0.00 | 41.67 | 2+1 |
| a | active | 2 | 62.50 | 25.00 | 50.00 | 2+1 |
| a | passive | 1 | 12.50 | 0.00 | 8.33 | 2+1 |

![Macro-average success](figures/macro_average.png)

## Per-task success per run

### a — active

| task | arms | run 1 | run 2 | success % (mean ± SD) |
|---|---|---|---|---|
| task_a1 | single | 4/4 | 3/4 | 87.50 ± 17.68 |
| task_a2 | single | 1/4 | 2/4 | 37.50 ± 17.68 |
| task_dual | dual | 0/4 | 1/4 | 12.50 ± 17.68 |

### a — passive

| task | arms | run 1 | success % (mean ± SD) |
|---|---|---|---|
| task_a1 | single | 1/4 | 25.00 (1 run) |
| task_a2 | single | 0/4 | 0.00 (1 run) |
| task_dual | dual | 0/4 | 0.00 (1 run) |

![a — active: per-task success](figures/success_a_active.png)

![a — passive: per-task success](figures/success_a_passive.png)

## Active vs passive camera protocol

### Sign test over non-tied families

| model | runs | families | non-tied | passive worse | passive better | ties | sign test p (two-sided) |
|---|---|---|---|---|---|---|---|
| a | run 1 | 3 | 2 | 2 | 0 | 1 | 0.5 |

### a — run 1

| task | active | passive | Δ (P − A) |
|---|---|---|---|
| task_a1 | 4/4 | 1/4 | -3 (-75.00 pp) |
| task_a2 | 1/4 | 0/4 | -1 (-25.00 pp) |
| task_dual | 0/4 | 0/4 | +0 (+0.00 pp) |

![a: active vs passive (run 1)](figures/active_passive_a.png)

## Subtask checkpoints (micro-average over scored episodes)

### Checkpoints reached / possible

| model | track | Single-arm reached/possible (%) | Dual-arm reached/possible (%) | All reached/possible (%) |
|---|---|---|---|---|
| a | active | 0/48 (0.00) | 0/24 (0.00) | 0/72 (0.00) |
| a | passive | 0/24 (0.00) | 0/12 (0.00) | 0/36 (0.00) |

## Steps, actions, tokens and cost

### Usage over scored episodes

| model | track | episodes | mean steps | camera actions / steps | invalid outputs / calls | invalid actions / robot actions | tokens | tokens / episode | cost USD | cost USD / episode |
|---|---|---|---|---|---|---|---|---|---|---|
| a | active | 24 | 0.0 | — | — | — | 0 | 0 | 0.00 | 0.0000 |
| a | passive | 12 | 0.0 | — | — | — | 0 | 0 | 0.00 | 0.0000 |
"""  # noqa: E501 (the report's own lines)


def test_base_sweep_report_is_unchanged(tmp_path):
    out = report(write(tmp_path, base_sweep()))
    md = (out / "report.md").read_text()
    assert not any(f"## {h}" in md for h in NEW_HEADINGS)
    expected = {"report.md", "report.html", "macro_average.md", "success_per_task.md",
                "active_passive.md", "usage.md", "checkpoints.md", "macro_average.csv",
                "macro_average_runs.csv", "success_per_task.csv", "active_passive.csv",
                "sign_test.csv", "usage.csv", "checkpoints.csv", "unscored.csv",
                "overall.md", "task_matrix.md", "overall.csv", "task_matrix.csv",
                "results.json", "episode_outcomes.csv"}  # fmt: skip
    assert {p.name for p in out.iterdir() if p.is_file()} == expected
    # the publication's views (tests/test_report_publication.py) come first; the rest as before
    start, end = md.index("## Overall success\n"), md.index("## Macro-average success\n")
    assert "## Task-by-model success\n" in md[start:end]
    assert md[:start] + md[end:] == BASE_REPORT_MD.replace(
        "{RESULTS}", str(tmp_path / "results.jsonl")
    )


def test_every_track_section_in_markdown_csv_and_html(tmp_path):
    lines = summary_sweep() + transfer_sweep() + long_sweep()
    run_dir = write(tmp_path, lines)
    write_learning(run_dir, "m", B1, status="learned", stop_reason="learned")
    out = report(run_dir)
    md, page = (out / "report.md").read_text(), (out / "report.html").read_text()
    for heading in NEW_HEADINGS:
        assert md.count(f"\n## {heading}\n") == 1 and page.count(f"<h2>{heading}</h2>") == 1
    for name in ("summary_source", "summary_cross_model", "summary_per_task", "learning_stage",
                 "transfer", "transfer_macro", "long_horizon"):  # fmt: skip
        assert (out / f"{name}.csv").stat().st_size > 0, name


def test_transfer_pair_with_an_all_skipped_side_gets_no_delta(tmp_path):
    # run 1: B1 4/4 -> H1 2/4; B2 2/4 -> H2 0/4, every H2 episode stopped before its first
    # step. H2 is left out of the macros: base 4/4 = 1, held-out 2/4, Δ -1/2 (1 run).
    lines = transfer_sweep()[:8] + transfer_sweep()[16:20]
    lines += [
        line("m", "transfer", H2, seed, 1, False, stop_reason="model_stop", steps_used=0)
        for seed in range(4)
    ]
    cells, _ = condition_cells(records(lines))
    (cmp,) = transfer_comparisons(cells, META)
    fams = {f.heldout: f for f in cmp.families}
    h2 = fams[H2]
    assert (h2.heldout_skipped, h2.skipped_side, h2.delta) == (4, "held-out", None)
    assert (fams[H1].skipped_side, fams[H1].delta) == (None, Fraction(-1, 2))
    assert cmp.skipped == (H2,)
    assert (cmp.base.mean, cmp.heldout.mean, cmp.delta.mean) == (1, Fraction(1, 2), Fraction(-1, 2))
    md = (report(write(tmp_path, lines)) / "report.md").read_text()
    assert f"| {B2} | {H2} | 50.00 (2/4) | 0.00 (0/4) | — (all held-out skipped) |" in md
    assert "shown without a Δ, every episode of the base or the held-out side skipped" in md
