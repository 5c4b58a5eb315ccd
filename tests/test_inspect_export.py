"""A sweep's records as inspect_ai logs (vabench/report/inspect_log.py), read back with
inspect_ai's own reader: one log per model and track, a sample per scored episode with its
messages (the frames the model saw, its replies), its score and its usage."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("inspect_ai", reason="the export's extra (vabench[inspect]; [test] has it)")

from inspect_ai.log import read_eval_log
from inspect_ai.model import ContentImage

from vabench.report.inspect_log import export, main
from vabench.run_layout import RESULTS
from vabench.sweep.__main__ import main as sweep

CONFIG = """\
name: inspect
models:
  - {name: local, api: openai_chat, base_url: embedded}
embedded_server: {policy: conversation_hash}
tracks: [active, passive]
tasks: [grasp_single_cube]
seeds: {verified: 2}
runs: 1
step_budget: 2
summaries: none
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("inspect")
    (root / "c.yaml").write_text(CONFIG)
    assert sweep([str(root / "c.yaml"), "--out", str(root / "run"), "--plain", "--no-report"]) == 0
    return root / "run"


def test_the_logs_read_back_with_inspect_ais_reader(run, tmp_path):
    paths = export(run, tmp_path / "logs")
    assert sorted(p.name for p in paths) == ["local_active.eval", "local_passive.eval"]
    ledger = [json.loads(x) for x in (run / RESULTS).read_text().splitlines()]
    for path in paths:
        log = read_eval_log(str(path), resolve_attachments=True)
        track = log.eval.task.split("/")[-1]
        mine = {(r["task"], r["seed"], r["run"]): r for r in ledger if r["track"] == track}
        assert log.status == "success" and log.eval.model == "vabench/local"
        assert log.samples is not None and len(log.samples) == len(mine) == 2
        wins = sum(r["success"] for r in mine.values())
        assert log.results.scores[0].metrics["accuracy"].value == wins / 2
        for sample in log.samples:
            task, seed, number = str(sample.id).split(":")
            r = mine[(task, int(seed), int(number))]
            assert sample.scores["success"].value == (1 if r["success"] else 0)
            assert sample.scores["success"].answer == r["stop_reason"]
            replies = [m for m in sample.messages if m.role == "assistant"]
            assert len(replies) == r["model_calls"]
            images = [
                c
                for m in sample.messages
                if m.role == "user" and not isinstance(m.content, str)
                for c in m.content
                if isinstance(c, ContentImage)
            ]
            per_view = 5 if track == "passive" else 1
            assert len(images) >= per_view and images[0].image.startswith("data:image/jpeg")
            usage = sample.model_usage["vabench/local"]
            assert usage.output_tokens == r["tokens"]["output"]


def test_without_images_and_errors_are_one_line(run, tmp_path, capsys):
    assert main([str(run), "--out", str(tmp_path / "small"), "--no-images"]) == 0
    log = read_eval_log(str(tmp_path / "small" / "local_active.eval"))
    assert log.samples and not any(
        isinstance(c, ContentImage)
        for m in log.samples[0].messages
        if not isinstance(m.content, str)
        for c in m.content
    )
    assert main([str(tmp_path / "nowhere"), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not found" in err[0]
