"""The scale benchmark (benchmarks/records_scale.py) at a CI size: its synthetic run is a run
directory the sweep, the report, the diagnostics and the viewer all read as a real one, and
every operation reports figures that agree with what the generator wrote. Timings are printed
by the benchmark, never asserted here."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import records_scale as bench

from vabench.run_layout import RunDir


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    root = tmp_path_factory.mktemp("scale")
    return root, bench.measure([200], root, list(bench.OPS), isolate=False)


def test_the_synthetic_run_reads_as_a_real_one(measured):
    root, _ = measured
    run = bench.synthetic(root, 200)  # made by `measure`: read back from its marker
    assert 190 <= run.planned <= 200 and run.finished == round(0.9 * run.planned)
    files = RunDir(run.run_dir)
    lines = [json.loads(x) for x in files.results.read_text().splitlines()]
    assert len(lines) == run.finished
    first = lines[0]
    episode = run.run_dir / first["episode_dir"]
    result = json.loads((episode / "result.json").read_text())
    assert {k: v for k, v in first.items() if k not in ("track", "episode_dir")} == result
    events = [json.loads(x) for x in (episode / "events.jsonl").read_text().splitlines()]
    assert (events[0]["type"], events[-1]["type"]) == ("episode_start", "end")
    assert events[-1]["status"] == first["status"] and events[0]["seed"] == first["seed"]
    frames = [f for e in events if e["type"] == "observation" for f in e["frames"]]
    assert frames and all((episode / f).read_bytes()[:2] == b"\xff\xd8" for f in frames)
    assert len(files.annotation_files()) == 3


def test_every_operation_reports_what_the_run_holds(measured):
    root, results = measured
    run = bench.synthetic(root, 200)
    by_op = {r["op"]: r for r in results}
    assert set(by_op) == set(bench.OPS)
    for r in results:
        assert r["seconds"] > 0 and r["peak_rss_mb"] >= r["base_rss_mb"] > 0
    resume = by_op["resume"]
    assert (resume["planned"], resume["finished"]) == (run.planned, run.finished)
    assert resume["pending"] == run.planned - run.finished
    assert by_op["dry_run"]["rc"] == 0
    assert f"{run.finished} of {run.planned} episodes" in by_op["dry_run"]["output_line"]
    assert by_op["report"]["files"] > 5
    assert by_op["diagnostics"]["rc"] == 0 and by_op["diagnostics"]["chars"] > 0
    viewer = by_op["viewer"]
    assert viewer["total"] == run.finished and viewer["statuses"] == [200, 200]
    assert 0 < viewer["page_first_byte_s"] <= viewer["page_full_s"]
    text = bench.table(results)
    for label in ("resume", "dry_run", "report", "diagnostics", "run page first byte"):
        assert label in text


def test_growth_is_per_ten_times_the_episodes():
    rows = [
        {"planned": 1000, "seconds": 1.0},
        {"planned": 10_000, "seconds": 10.0},
        {"planned": 100_000, "seconds": 1000.0},
    ]
    assert bench.growth(rows, "seconds") == ["", "10.0x", "100.0x"]
