"""What the sweep promises across invocations (docs/RELIABILITY.md), each through the command:

- a run directory belongs to one plan: resuming it with a config whose plan differs is refused,
  naming the differing fields, before anything runs;
- an endpoint that refuses the sweep's requests (a wrong key, an unknown model) stops the sweep
  within its first calls, naming the model and the key's variable; nothing is recorded for the
  episodes it touched, and the same command runs them once the endpoint is fixed;
- a duplicate ledger record (two writers raced) is reported and collapsed on resume, not fatal.
"""

from __future__ import annotations

import json
from pathlib import Path

from vabench.sweep.__main__ import main
from vabench.sweep.results import LEDGER

CONFIG = """\
name: reliability
models:
  - name: local
    api: {api}
    base_url: embedded
    retry: {{max_attempts: 2, backoff_base_s: 0.01, backoff_max_s: 0.02}}
embedded_server: {server}
tracks: [active]
tasks: [grasp_single_cube]
seeds: {{verified: 2}}
runs: 1
step_budget: {budget}
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
"""


def write(
    path: Path,
    *,
    server: str = "{policy: conversation_hash}",
    budget: int = 2,
    api: str = "openai_chat",
) -> Path:
    path.write_text(CONFIG.format(server=server, budget=budget, api=api))
    return path


def ledger_lines(run_dir: Path) -> list[dict]:
    path = run_dir / LEDGER
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def test_resuming_with_another_plan_is_refused_naming_the_fields(tmp_path, capsys):
    out = tmp_path / "out"
    cfg = write(tmp_path / "a.yaml", budget=2)
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    before = (out / LEDGER).read_bytes()
    assert len(ledger_lines(out)) == 2
    capsys.readouterr()

    changed = write(tmp_path / "b.yaml", budget=3)
    assert main([str(changed), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "step_budget: 2 -> 3" in err and "--out" in err
    assert (out / LEDGER).read_bytes() == before  # nothing ran, nothing was written

    # what does not decide the plan (retries, render workers) may change
    same = tmp_path / "c.yaml"
    same.write_text(cfg.read_text().replace("max_attempts: 2", "max_attempts: 3"))
    assert main([str(same), "--out", str(out), "--plain", "--no-report"]) == 0
    assert (out / LEDGER).read_bytes() == before
