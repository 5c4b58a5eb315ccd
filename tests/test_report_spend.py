"""The report's bill counts every call the provider answered (defect E): a sweep whose episodes
fail for infrastructure reasons after some successful calls, and are run again, reports the
spend of the failed attempts too, equal to what the embedded server logged as answered."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest

from vabench.sweep.__main__ import main

PRICES = {"input": 3.0, "output": 15.0}  # US dollars per million tokens
CONFIG = """\
name: spend
models:
  - name: local
    api: openai_chat
    base_url: embedded
    prices: {prices}
    retry: {{max_attempts: 1}}
embedded_server:
  policy: conversation_hash
  simulate_cache: false
  seed: 7
  faults: {{rates: {{server_error: 0.15}}}}
  log_path: {log}
tracks: [active]
summaries: none
tasks: [grasp_single_cube]
seeds: {{verified: 4}}
runs: 1
step_budget: 5
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
retries: {{infrastructure_rounds: 3}}
"""


def test_the_bill_counts_the_calls_of_attempts_that_were_run_again(tmp_path):
    log = tmp_path / "server.jsonl"
    cfg = tmp_path / "spend.yaml"
    cfg.write_text(CONFIG.format(prices=json.dumps(PRICES), log=log))
    out = tmp_path / "out"
    main([str(cfg), "--out", str(out), "--plain"])

    answered = [r for r in map(json.loads, log.read_text().splitlines()) if r["status"] == 200]
    truth = math.fsum(
        (r["input_tokens"] * PRICES["input"] + r["output_tokens"] * PRICES["output"]) / 1e6
        for r in answered
    )
    ledger = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    recorded = math.fsum(r["cost_usd"] for r in ledger)
    retried = (out / "infrastructure.jsonl").read_text().splitlines()
    assert retried, "no infrastructure failure was run again: the fault seed needs changing"
    assert recorded < truth  # the records alone understate the bill

    rows = list(csv.DictReader((out / "report" / "spend.csv").open()))
    by_source = {r["source"]: r for r in rows if r["model"] == "local"}
    total = by_source.pop("total")  # the last row of each model sums its sources
    billed = math.fsum(float(r["cost_usd"]) for r in by_source.values())
    assert float(total["cost_usd"]) == pytest.approx(billed, abs=1e-9)
    for column in ("items", "tokens_input", "tokens_output"):
        assert int(total[column]) == sum(int(r[column]) for r in by_source.values()), column
    assert billed == pytest.approx(truth, abs=1e-5)  # results round cost to 1e-6 per episode
    run_again = by_source["infrastructure failures run again"]
    assert int(run_again["items"]) == len(retried) and float(run_again["cost_usd"]) > 0
    tokens = sum(int(r["tokens_input"]) + int(r["tokens_output"]) for r in by_source.values())
    assert tokens == sum(r["input_tokens"] + r["output_tokens"] for r in answered)
    report = (out / "report" / "report.md").read_text()
    assert "Spend of every call" in report
    (total_row,) = [x for x in report.splitlines() if x.startswith("| local | total |")]
    cells = [c.strip() for c in total_row.strip("|").split("|")]
    assert cells[2] == total["items"] and cells[3] and cells[3] != "0"  # records, tokens
    html = (out / "report" / "report.html").read_text()
    assert f"<td>total</td><td>{total['items']}</td><td>{cells[3]}</td>" in html
    assert Path(out / "report" / "spend.md").exists()
