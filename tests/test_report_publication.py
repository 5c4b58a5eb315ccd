"""The paper's headline views, results.json and the leaderboard over run directories.

Hand-made run directories (results.jsonl, and sweep.yaml where comparability is checked) keep
these fast; the 12-model, 3-run run and the annotated one are benchmarks/synthetic_runs.py's.
Expected numbers are worked out by hand in the comments.
"""

from __future__ import annotations

import asyncio
import csv
import json
import math
import shutil
import sys
from pathlib import Path

import aiohttp
import pytest
import yaml
from aiohttp import web

from vabench.report import published as P
from vabench.report.__main__ import main
from vabench.report.build import generate
from vabench.view.app import Viewer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from synthetic_runs import make_run

CUBE, BELL, POT = "grasp_single_cube", "click_bell_right", "lift_pot"
FIGURES = ("overall.png", "task_matrix.png", "task_matrix_published.png")


def line(model: str, task: str, seed: int, run: int, success: bool, **fields) -> dict:
    return {
        "v": 1,
        "track": "active",
        "episode_dir": f"episodes/{model}/active/{task}/seed_{seed}/run_{run}",
        "task": task,
        "seed": seed,
        "model": model,
        "protocol": "active",
        "run": run,
        "status": "success" if success else "failure",
        "success": success,
        "stop_reason": "success" if success else "budget_exhausted",
        "step_budget": 50,
        "n_checkpoints": 2,
        **fields,
    }


def sweep(model: str, runs: dict[int, dict[str, int]], seeds: int = 4) -> list[dict]:
    """Per run, the first `k` of `seeds` episodes of each task succeed."""
    return [
        line(model, task, seed, run, seed < k)
        for run, successes in runs.items()
        for task, k in successes.items()
        for seed in range(seeds)
    ]


# model "m": run 1 cube 4/4, bell 2/4, pot 0/4 -> all (1 + 1/2 + 0)/3 = 1/2, single 3/4
#            run 2 cube 3/4, bell 1/4, pot 1/4 -> all 5/12, single 1/2, dual 1/4
#            run 3 cube 2/4, bell 2/4, pot 2/4 -> all 1/2, single 1/2, dual 1/2
# all: mean (6 + 5 + 6)/36 = 17/36; deviations 1/36, -2/36, 1/36: variance (1+4+1)/1296 / 2
# = 1/432; single: mean 7/12, deviations 2/12, -1/12, -1/12: variance (4+1+1)/144 / 2 = 1/48
M_RUNS = {
    1: {CUBE: 4, BELL: 2, POT: 0},
    2: {CUBE: 3, BELL: 1, POT: 1},
    3: {CUBE: 2, BELL: 2, POT: 2},
}
N_RUNS = {1: {CUBE: 1, BELL: 0, POT: 0}, 2: {CUBE: 0, BELL: 0, POT: 0}}


def config_doc(models: list[str], width: int = 320) -> dict:
    return {
        "name": "t",
        "models": [{"name": m, "api": "openai_chat", "base_url": "embedded"} for m in models],
        "tracks": ["active"],
        "tasks": [BELL, CUBE, POT],
        "seeds": {t: [0, 1, 2, 3] for t in (BELL, CUBE, POT)},
        "simulator": {"backend": "c"},
        "render": {"backend": "gl", "width": width, "height": 240, "quality": 95},
    }


def write(run_dir: Path, lines: list[dict], doc: dict | None = None) -> Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "results.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    if doc is not None:
        (run_dir / "sweep.yaml").write_text(yaml.safe_dump(doc))
    return run_dir


def read_csv(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


def test_overall_is_the_paper_formula_on_a_hand_computed_case(tmp_path):
    out = generate(write(tmp_path, sweep("m", M_RUNS))).directory
    rows = {(r["model"], r["source"], r["subset"]): r for r in read_csv(out / "overall.csv")}
    mine = rows[("m", "this run", "all")]
    assert float(mine["mean"]) == pytest.approx(17 / 36, rel=1e-12)
    assert float(mine["sd"]) == pytest.approx(math.sqrt(1 / 432), rel=1e-12)
    single = rows[("m", "this run", "single")]
    assert float(single["mean"]) == pytest.approx(7 / 12, rel=1e-12)
    assert float(single["sd"]) == pytest.approx(math.sqrt(1 / 48), rel=1e-12)
    doc = json.loads((out / "results.json").read_text())
    macro = {(m["model"], m["subset"]): m for m in doc["macro"]}
    assert macro[("m", "all")]["mean"] == pytest.approx(17 / 36, rel=1e-12)
    assert macro[("m", "all")]["runs"] == 3
    # the published rows: the paper's tab:main-results, as printed
    ref = rows[("Qwen3.8-max", P.REFERENCE_SHORT, "all")]
    assert (float(ref["mean"]), float(ref["sd"])) == (0.5393, 0.0317)
    for name in FIGURES:
        assert (out / "figures" / name).read_bytes()[:4] == b"\x89PNG"
    page = (out / "report.html").read_text()
    assert page.count("<tr class='reference'>") == 12 + 14  # overall rows + per-task rows
    assert P.REFERENCE_LABEL in page


def test_published_tables_are_consistent_with_each_other():
    # the per-task means of each model average to its printed all-14 mean (rounding: 0.01)
    assert list(P.PER_TASK) == list(P.PAPER_TASK_ORDER) and len(P.MODELS) == 12
    for m in P.MODELS:
        mean = sum(P.PER_TASK[t][m][0] for t in P.PAPER_TASK_ORDER) / 14
        assert mean == pytest.approx(P.OVERALL[m]["all"][0], abs=0.01), m
        single = sum(P.PER_TASK[t][m][0] for t in P.PAPER_TASK_ORDER[:11]) / 11
        assert single == pytest.approx(P.OVERALL[m]["single"][0], abs=0.01), m


def test_reference_false_leaves_the_published_rows_out(tmp_path):
    doc = {**config_doc(["m"]), "report": {"reference": False}}
    out = generate(write(tmp_path, sweep("m", M_RUNS), doc)).directory
    assert {r["source"] for r in read_csv(out / "overall.csv")} == {"this run"}
    assert not (out / "figures" / "task_matrix_published.png").exists()
    assert json.loads((out / "results.json").read_text())["reference"] is None
    assert P.REFERENCE_LABEL not in (out / "report.html").read_text()


def test_results_json_validates_and_reads_back(tmp_path):
    jsonschema = pytest.importorskip("jsonschema")
    lines = sweep("m", M_RUNS)
    lines[0] |= {"invalid_outputs": 2}
    lines[1] |= {"refusals": 1, "truncations": 3}  # counters a newer result may carry
    lines.append({**line("m", CUBE, 9, 1, False), "status": "infrastructure_error"})
    out = generate(write(tmp_path, lines, config_doc(["m"]))).directory
    doc = json.loads((out / "results.json").read_text())
    schema = json.loads((Path(P.__file__).with_name("results.schema.json")).read_text())
    jsonschema.validate(doc, schema)
    assert len(doc["episodes"]) == len(lines)
    (m,) = doc["models"]
    assert (m["scored"], m["unscored"], m["invalid_outputs"]) == (36, 1, 2)
    assert m["empty_replies"] == 0
    prov = doc["provenance"]
    assert prov["physics_backend"] == "c" and prov["renderer"] == "gl"
    assert prov["comparability"]["image"] == {
        "width": 320,
        "height": 240,
        "jpeg_quality": 95,
        "jpeg_subsampling": None,
    }
    assert prov["comparability"]["seeds"][CUBE] == [0, 1, 2, 3]
    assert len(prov["config_sha256"]) == 64 and prov["protocol_version"]
    episodes = read_csv(out / "episode_outcomes.csv")
    assert len(episodes) == len(lines) and {"stop_reason", "refusals"} <= set(episodes[0])
    bad = {**doc, "episodes": [{**doc["episodes"][0], "seed": "one"}]}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, schema)


def aggregates(out: Path) -> dict:
    doc = json.loads((out / "results.json").read_text())
    keep = ("episodes", "task_runs", "tasks", "macro_runs", "macro", "models", "reference")
    return {k: doc[k] for k in keep}


def test_a_leaderboard_of_two_sweeps_equals_one_sweep_of_both(tmp_path):
    both = write(tmp_path / "both", sweep("m", M_RUNS) + sweep("n", N_RUNS), config_doc(["m", "n"]))
    a = write(tmp_path / "runs" / "a", sweep("m", M_RUNS), config_doc(["m"]))
    b = write(tmp_path / "runs" / "b", sweep("n", N_RUNS), config_doc(["n"]))
    one = generate(both).directory
    assert main([str(a), str(b), "--out", str(tmp_path / "board")]) == 0
    assert main([str(tmp_path / "runs"), "--out", str(tmp_path / "board2")]) == 0  # a directory
    for board in (tmp_path / "board", tmp_path / "board2"):
        assert aggregates(board) == aggregates(one)
        for name in ("overall.csv", "task_matrix.csv", "macro_average.csv", "success_per_task.csv"):
            assert (board / name).read_text() == (one / name).read_text(), name
        sources = json.loads((board / "results.json").read_text())["provenance"]["sources"]
        assert [s["run_dir"] for s in sources] == [str(a), str(b)]


def test_a_mismatched_pair_is_refused_in_one_line_or_marked(tmp_path, capsys):
    a = write(tmp_path / "a", sweep("m", M_RUNS), config_doc(["m"]))
    b = write(tmp_path / "b", sweep("n", N_RUNS), config_doc(["n"], width=640))
    assert main([str(a), str(b), "--out", str(tmp_path / "board")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "image differs" in err and "--allow-mismatch" in err
    assert not (tmp_path / "board" / "results.json").exists()
    assert main([str(a), str(b), "--out", str(tmp_path / "board"), "--allow-mismatch"]) == 0
    rows = read_csv(tmp_path / "board" / "overall.csv")
    assert {r["model"] for r in rows if r["source"] == "this run"} == {"m", "n"}
    md = (tmp_path / "board" / "overall.md").read_text()
    assert "| n | active | this run | 2 |" in md and md.count("| image |") == 1
    models = json.loads((tmp_path / "board" / "results.json").read_text())["models"]
    assert {m["model"]: m["mismatch"] for m in models} == {"m": "", "n": "image"}


def test_sweeps_of_another_action_timing_are_not_comparable(tmp_path, capsys):
    """Runs whose actions end differently (`simulator.action_end`) never share a table
    silently; a sweep.yaml without the field (written before it existed) ran fixed actions."""
    old = config_doc(["m"])
    paced = config_doc(["n"]) | {"simulator": {"backend": "c", "action_end": "paced"}}
    fixed = config_doc(["o"]) | {"simulator": {"backend": "c", "action_end": "fixed"}}
    a = write(tmp_path / "a", sweep("m", M_RUNS), old)
    b = write(tmp_path / "b", sweep("n", N_RUNS), paced)
    c = write(tmp_path / "c", sweep("o", N_RUNS), fixed)
    assert main([str(a), str(b), "--out", str(tmp_path / "board")]) == 2
    err = capsys.readouterr().err
    assert "action_end differs" in err and '"fixed" vs "paced"' in err
    assert main([str(a), str(c), "--out", str(tmp_path / "board")]) == 0


def test_the_same_model_in_two_sweeps_pools_disjoint_runs_only(tmp_path, capsys):
    whole = generate(write(tmp_path / "whole", sweep("m", M_RUNS), config_doc(["m"]))).directory
    first = write(tmp_path / "r1", sweep("m", {1: M_RUNS[1]}), config_doc(["m"]))
    rest = write(tmp_path / "r23", sweep("m", {2: M_RUNS[2], 3: M_RUNS[3]}), config_doc(["m"]))
    assert main([str(first), str(rest), "--out", str(tmp_path / "board")]) == 0
    assert aggregates(tmp_path / "board") == aggregates(whole)
    again = write(tmp_path / "again", sweep("m", {1: M_RUNS[1]}), config_doc(["m"]))
    assert main([str(first), str(again), "--out", str(tmp_path / "b2")]) == 2
    err = capsys.readouterr().err
    assert "model 'm' has run(s) [1] in both" in err


def serve(app: web.Application, body):
    async def go():
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        try:
            url = f"http://127.0.0.1:{runner.addresses[0][1]}"
            async with aiohttp.ClientSession(url) as http:
                return await body(http)
        finally:
            await runner.cleanup()

    return asyncio.run(go())


def same(percent: str, expected: float | None) -> None:
    """A capability cell equals the diagnostics table's: both NA, or the same number."""
    if expected is None:
        assert percent == ""
    else:
        assert float(percent) == pytest.approx(expected, rel=1e-12)


def diag_rows(out: Path) -> dict:
    """Per condition and criterion, the diagnostics table's rate in % (its CSV)."""
    return {
        (r["model"], r["track"], r["criterion"]): None
        if r["rate"] == ""
        else 100 * float(r["rate"])
        for r in read_csv(out / "diagnostics.csv")
        if r["task"] == "" and len(r["criterion"]) == 2
    }


def test_the_radar_numbers_are_the_diagnostics_tables(tmp_path):
    run = make_run(tmp_path / "s", 120, models=2, runs=2, annotated=0.6, annotate_run=1)
    out = generate(run.run_dir).directory
    diag = diag_rows(out)
    cap = read_csv(out / "capability.csv")
    assert {(r["model"], r["track"]) for r in cap} == {("model-0", "active"), ("model-1", "active")}
    for r in cap:
        same(r["percent"], diag[(r["model"], r["track"], r["criterion"])])
        assert r["runs"] == "1"  # the annotated run, named
    page = (out / "report.html").read_text()
    assert 'alt="Capability profile per annotated condition"' in page
    assert "<td>model-0</td><td>active</td><td>run 1</td>" in page  # the annotated run, named
    for name in ("capability_radar.png", "radar_model-0_active.png"):
        assert (out / "figures" / name).read_bytes()[:4] == b"\x89PNG"

    # the viewer's run page shows the same radar beside a model's episodes, over loopback
    async def body(http):
        ok = await http.get("/api/radar", params={"model": "model-0"})
        none = await http.get("/api/radar", params={"model": "nobody"})
        page = await (await http.get("/")).text()
        return ok.status, await ok.read(), none.status, page

    status, png, missing, page = serve(Viewer(run.run_dir).app(), body)
    assert status == 200 and png == (out / "figures" / "radar_model-0_active.png").read_bytes()
    assert missing == 404 and 'id="radar-img"' in page


def test_a_twelve_model_three_run_report_holds_the_figures_and_reference_rows(tmp_path):
    run = make_run(tmp_path / "s", 1300, models=12, runs=3, annotated=0.5, annotate_run=1)
    out = generate(run.run_dir).directory
    for name in (*FIGURES, "capability_radar.png"):
        assert (out / "figures" / name).read_bytes()[:4] == b"\x89PNG"
    overall = read_csv(out / "overall.csv")
    assert len({r["model"] for r in overall if r["source"] == "this run"}) == 12
    assert len({r["model"] for r in overall if r["source"] == P.REFERENCE_SHORT}) == 12
    assert len({r["model"] for r in read_csv(out / "capability.csv")}) == 12
    shutil.copytree(out / "figures", tmp_path / "figures")


def test_the_smoke_sweeps_report_holds_the_three_views_and_the_reference_rows(tmp_path):
    """A real run (diag_util: configs/smoke.yaml cut to one task and seed), its active episode
    judged by three annotators as the viewer writes judgments."""
    import random

    from diag_util import ACTIVE, copy_run
    from synthetic_runs import _judgments

    from vabench.run_layout import RunDir

    (tmp_path / "pristine").mkdir()
    run_dir = copy_run(tmp_path / "pristine", tmp_path / "run")
    files = RunDir(run_dir)
    files.annotations.mkdir(exist_ok=True)
    for annotator, lines in _judgments(ACTIVE, random.Random(3), 1795800000.0).items():
        text = "".join(json.dumps(x) + "\n" for x in lines)
        files.annotation_file(annotator).write_text(text, encoding="utf-8")
    out = generate(run_dir).directory
    for name in (*FIGURES, "capability_radar.png", "radar_local_active.png"):
        assert (out / "figures" / name).read_bytes()[:4] == b"\x89PNG", name
    overall = read_csv(out / "overall.csv")
    assert {r["model"] for r in overall if r["source"] == "this run"} == {"local"}
    assert len({r["model"] for r in overall if r["source"] == P.REFERENCE_SHORT}) == 12
    (cap,) = {(r["model"], r["track"], r["runs"]) for r in read_csv(out / "capability.csv")}
    assert cap == ("local", "active", "1")
    diag = diag_rows(out)
    for r in read_csv(out / "capability.csv"):
        same(r["percent"], diag[("local", "active", r["criterion"])])
    doc = json.loads((out / "results.json").read_text())
    assert doc["provenance"]["physics_backend"] == "c" and doc["provenance"]["config_sha256"]


def test_the_config_field_reaches_the_run_directory(tmp_path):
    """`report.reference` is a config field (refused when not a boolean), written to
    sweep.yaml by the sweep (`SweepConfig.document`), where the report reads it."""
    from vabench.config import SweepConfigError, load_config
    from vabench.report.build import reference_wanted

    doc = {**config_doc(["m"]), "seeds": [1000], "report": {"reference": False}}
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(doc))
    config = load_config(path, environ={})
    assert config.report.reference is False
    write(tmp_path / "run", [], config.document())
    assert reference_wanted(tmp_path / "run") is False
    path.write_text(yaml.safe_dump({**doc, "report": {"reference": "maybe"}}))
    with pytest.raises(SweepConfigError, match=r"report\.reference"):
        load_config(path, environ={})


def test_an_unfinished_sweep_of_a_leaderboard_is_said_first(tmp_path, capsys):
    a = write(tmp_path / "a", sweep("m", M_RUNS), config_doc(["m"]))
    b = write(tmp_path / "b", sweep("n", N_RUNS), config_doc(["n"]))
    plan = {"v": 2, "fields": {}, "episodes": [f"n/active/t/{i}/1" for i in range(30)]}
    (b / "plan.json").write_text(json.dumps(plan))  # 30 planned, 24 scored
    assert main([str(a), str(b), "--out", str(tmp_path / "board")]) == 0
    page = (tmp_path / "board" / "report.html").read_text()
    assert f"{b}: incomplete sweep: 24 of 30 planned episodes scored" in page
    assert f"{a}: incomplete" not in page
