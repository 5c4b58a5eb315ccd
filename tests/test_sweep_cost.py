"""What a sweep costs, through the command: a model without prices shows "price not
set", never "$0.00", in the dry-run, the live display and the report; the embedded server's
unpriced models show "no cost"; `limits.max_cost_usd` (of the sweep, of a model) sends no call
that could cross it, stops without recording the episodes it ends, says which cap and at what
spend, and the same command with a higher cap resumes, counting the spend already recorded.

The "paid" models are the embedded server with prices set (it reports usage like a provider);
the unpriced endpoint that is not the embedded server is a `LocalServer` on loopback, run in a
thread of the test.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from vabench.llm_pool.server import ServerConfig
from vabench.llm_pool.testing import server_in_thread
from vabench.report.spend import bill
from vabench.run_layout import RESULTS
from vabench.sweep.__main__ import main

BODY = """\
embedded_server: {policy: conversation_hash}
tracks: [active]
tasks: [grasp_single_cube]
seeds: {verified: 2}
runs: 1
step_budget: 2
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
"""
# $1000 per million tokens: a call of ~1,500 tokens costs ~$1.5, so caps of a few dollars stop
# a tiny sweep part way; 200 output tokens keep a call's upper bound near its real cost.
PAID = (
    "  - {name: %s, api: openai_chat, base_url: embedded, prices: {input: 1000, output: 1000},"
    " generation: {max_output_tokens: 200}%s}\n"
)


def write(path: Path, models: str, extra: str = "") -> Path:
    path.write_text(f"name: cost\nmodels:\n{models}{BODY}{extra}")
    return path


def paid(name: str, cap: float | None = None) -> str:
    return PAID % (name, "" if cap is None else f", limits: {{max_cost_usd: {cap}}}")


def ledger(run_dir: Path) -> list[dict]:
    path = run_dir / RESULTS
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


@pytest.fixture
def outside_server() -> Iterator[str]:
    """A real endpoint the sweep does not start (its URL): a model pointed at it is not the
    embedded server, so without prices its cost is unknown."""
    with server_in_thread(ServerConfig(policy="conversation_hash")) as server:
        yield server.base_url("openai_chat")


def test_dry_run_says_price_not_set_never_zero_dollars(tmp_path, capsys):
    models = (
        "  - {name: gpt, api: openai_chat, model: gpt-5, base_url: http://127.0.0.1:9/v1}\n"
        "  - {name: local, api: openai_chat, base_url: embedded}\n" + paid("priced")
    )
    cfg = write(tmp_path / "c.yaml", models)
    assert main([str(cfg), "--out", str(tmp_path / "out"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line for line in out.splitlines() if line.strip()}
    assert rows["gpt"].endswith("price not set")
    assert rows["local"].endswith("no cost (embedded server)")
    assert "price not set" not in rows["priced"] and "no cost" not in rows["priced"]
    assert rows["total"].endswith(" + price not set (gpt)")
    assert "0.00" not in rows["gpt"] and "0.00" not in rows["local"]


def test_display_and_report_say_price_not_set(tmp_path, capsys, outside_server):
    models = f"  - {{name: unpriced, api: openai_chat, base_url: '{outside_server}'}}\n"
    out = tmp_path / "out"
    cfg = write(tmp_path / "c.yaml", models)
    assert main([str(cfg), "--out", str(out), "--plain"]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if " cost: episodes " in x]
    assert lines and all("tokens, price not set |" in x for x in lines), lines
    assert not any("$" in x for x in lines)
    usage = (out / "report" / "usage.md").read_text()
    row = next(x for x in usage.splitlines() if x.startswith("| unpriced | active |"))
    assert row.endswith("| price not set | price not set |") and "0.00" not in row
    spend = (out / "report" / "spend.md").read_text()
    (total,) = [x for x in spend.splitlines() if x.startswith("| unpriced | total | ")]
    assert re.fullmatch(r"\| unpriced \| total \| \d+ \| [\d,]+ \| price not set \|", total)
    assert "0.0000" not in spend
    import csv  # the CSVs leave an unpriced cost empty: a 0.0 would read as free

    for name, columns in (
        ("usage", ("cost_usd", "cost_usd_per_episode")),
        ("spend", ("cost_usd",)),
    ):
        with open(out / "report" / f"{name}.csv", newline="") as f:
            rows = [r for r in csv.DictReader(f) if r["model"] == "unpriced"]
        assert rows and all(r[c] == "" for r in rows for c in columns), (name, rows)


def test_a_models_cap_stops_only_that_model_and_a_higher_cap_resumes(tmp_path, capsys):
    out = tmp_path / "out"
    free = "  - {name: free, api: openai_chat, base_url: embedded}\n"
    cfg = write(tmp_path / "c.yaml", paid("paid", 6) + free)
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "stopped: limits.max_cost_usd of model 'paid' ($6) reached at $" in err
    assert "Raise the cap and run the same command to resume" in err
    first = ledger(out)
    assert sorted(r["model"] for r in first).count("free") == 2  # the other model went on
    assert sum(r["model"] == "paid" for r in first) < 2
    spent = bill(out).total("paid")
    assert 0 < spent <= 6  # never crossed: every call's upper bound was held before it went

    higher = write(tmp_path / "d.yaml", paid("paid", 1000) + free)
    assert main([str(higher), "--out", str(out), "--plain", "--no-report"]) == 0
    after = ledger(out)
    keys = [(r["model"], r["seed"]) for r in after]
    assert len(after) == 4 and len(set(keys)) == 4  # resumed: each episode recorded once
    assert after[: len(first)] == first


def test_the_sweeps_cap_stops_every_model_counting_the_recorded_spend(tmp_path, capsys):
    out = tmp_path / "out"
    models = paid("paid") + paid("other")
    cfg = write(tmp_path / "a.yaml", models, "limits: {max_cost_usd: 8}\n")
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "stopped: limits.max_cost_usd of the sweep ($8) reached at $" in err
    first = ledger(out)
    assert len(first) < 4
    total = bill(out).total("paid") + bill(out).total("other")
    assert 0 < total <= 8

    # The same command again: what the run directory already spent counts towards the cap, so
    # it stops again without passing it (counting from zero it would spend up to $8 more).
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 2
    assert "limits.max_cost_usd of the sweep ($8) reached" in capsys.readouterr().err
    assert bill(out).total("paid") + bill(out).total("other") <= 8

    higher = write(tmp_path / "b.yaml", models, "limits: {max_cost_usd: 1000}\n")
    assert main([str(higher), "--out", str(out), "--plain", "--no-report"]) == 0
    after = ledger(out)
    assert len(after) == 4 and len({(r["model"], r["seed"]) for r in after}) == 4
    assert after[: len(first)] == first


@pytest.mark.parametrize(
    ("extra", "model", "expected"),
    [
        ("limits: {max_cost_usd: -1}\n", "", "limits.max_cost_usd: must be more than 0"),
        (
            "limits: {max_cost_usd: lots}\n",
            "",
            "limits.max_cost_usd: must be a number",
        ),
        (
            "limits: {max_cost_usd: 5}\n",
            "",
            "limits.max_cost_usd: max_cost_usd needs prices for model 'gpt' (models[0].prices)",
        ),
        (
            "",
            ", limits: {max_cost_usd: 5}",
            "models[0].limits.max_cost_usd: max_cost_usd needs prices for model 'gpt'",
        ),
        ("", ", limits: {max_cost_usd: 0}", "models[0].limits.max_cost_usd: must be more than 0"),
    ],
)
def test_a_bad_cap_is_one_line_naming_the_field(tmp_path, capsys, extra, model, expected):
    models = (
        f"  - {{name: gpt, api: openai_chat, base_url: http://127.0.0.1:9/v1{model}}}\n"
        "  - {name: local, api: openai_chat, base_url: embedded}\n"
    )
    cfg = write(tmp_path / "c.yaml", models, extra)
    assert main([str(cfg), "--out", str(tmp_path / "out"), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert expected in err and "Traceback" not in err


def test_the_example_models_carry_dated_list_prices():
    import yaml

    from vabench.llm_pool.config import load_endpoints

    path = Path(__file__).parents[1] / "configs" / "models.example.yaml"
    text = path.read_text()
    models = {m.name: m for m in load_endpoints(yaml.safe_load(text)["models"])}
    assert models["gpt"].prices is not None and models["gpt"].prices.output > 0
    assert models["claude"].prices is not None and models["claude"].prices.output > 0
    assert "list prices as of" in text and "check the provider's pricing page" in text.lower()


def test_a_cap_holds_across_two_worker_processes(tmp_path, capsys):
    """Two cells in two worker processes, one cap: every call's upper bound is reserved on
    the sweep's limit board, so together they stop at the cap (each counting alone, each
    would spend up to it)."""
    two_tasks = BODY.replace("[grasp_single_cube]", "[grasp_single_cube, grasp_single_pen]")
    out = tmp_path / "out"
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        f"name: cost\nmodels:\n{paid('paid', 5)}{two_tasks}"
        "executor: {kind: processes, max_tasks: 2}\n"
    )
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "stopped: limits.max_cost_usd of model 'paid' ($5) reached at $" in err
    assert 0 < bill(out).total("paid") <= 5
    keys = [(r["task"], r["seed"]) for r in ledger(out)]
    assert len(keys) == len(set(keys))


def test_auto_keeps_its_layout_with_a_cap(tmp_path):
    from vabench.config import load_config
    from vabench.config.choices import Machine, choose

    cfg = write(tmp_path / "c.yaml", paid("priced", cap=5))
    chosen = choose(load_config(cfg, environ={}), Machine(32, ()))
    assert chosen.executor.kind == "processes" and chosen.executor.max_tasks == 32
