"""The automatic judge on a real smoke run, through the real LLM pool and the embedded server
(`rubric_judge`): both stages, judgments written as an annotator's, the agreement table
computed from them, and the privilege boundary: no request a judge receives holds an
evaluator-only field, value or identifier of the episode."""

from __future__ import annotations

import asyncio
import json

import pytest
from diag_util import ACTIVE, PASSIVE, copy_run

from vabench.agent.visibility import episode_secrets, find_leaks
from vabench.diagnostics import sections as report_diagnostics
from vabench.diagnostics.__main__ import main
from vabench.diagnostics.criteria import CRITERION_CODES, GATE_CODES
from vabench.diagnostics.episodes import RunIndex
from vabench.diagnostics.judge import run_judges, system_prompt
from vabench.diagnostics.store import AnnotationStore
from vabench.llm_pool import LLMPool
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.tasks import get_task


@pytest.fixture
def run(tmp_path_factory, tmp_path):
    return copy_run(tmp_path_factory.getbasetemp(), tmp_path / "run")


async def judge_captured(index, api, **kwargs):
    server = LocalServer(ServerConfig(policy="rubric_judge"), capture_bodies=True)
    async with server:
        endpoint = server.endpoint_config("judge", api)
        async with LLMPool([endpoint]) as pool:
            report = await run_judges(index, pool, "judge", **kwargs)
    return report, server.bodies


def secrets_of(index, episode):
    """What the evaluator knew: every object position recorded, the seed, the task's latch and
    checkpoint names, the object names, the predicate's check names."""
    events = index.events(episode)
    positions = {}
    checks = set()
    for e in events:
        for name, pose in (e.get("objects") or {}).items():
            positions[f"{name}@{e['seq']}"] = pose["pos"]
        checks |= set(e.get("checks") or {})
    task = get_task(index.get(episode).result.task)
    names = {n.split("@")[0] for n in positions}
    identifiers = [*task.latches, *task.checkpoints, *task.variants, *names, *checks]
    return episode_secrets(positions, index.get(episode).result.seed, None, identifiers)


@pytest.mark.parametrize("api", ["openai_chat", "anthropic"])
def test_judge_requests_hold_no_evaluator_only_field(run, api):
    index = RunIndex.load(run)
    report, bodies = asyncio.run(judge_captured(index, api, judges=2))
    assert report.failures == [] and report.judged == 2 * 2
    assert len(bodies) == 2 * 2 * 2  # 2 judges x 2 episodes x 2 stages
    secrets = {e: secrets_of(index, e) for e in (ACTIVE, PASSIVE)}
    assert any(s.word == "cube" or s.name.startswith("object") for s in secrets[ACTIVE])
    for _, raw in bodies:
        text = raw.decode()
        episode = PASSIVE if "Camera protocol: passive" in text else ACTIVE
        assert find_leaks(raw, secrets[episode]) == [], episode
        assert "Task instruction: Pick up the red cube" in text
        assert "image/jpeg" in text  # the images the model saw go along


def test_the_leak_check_catches_an_evaluator_field(run):
    # The same check on the same bodies fails once an evaluator-only field is put in: the
    # test above can fail.
    index = RunIndex.load(run)
    _, bodies = asyncio.run(judge_captured(index, "openai_chat", judges=1, episodes=[ACTIVE]))
    body = json.loads(bodies[0][1])
    action = next(e for e in index.events(ACTIVE) if e["type"] == "action")
    body["messages"][-1]["content"][0]["text"] += json.dumps({"checks": action["checks"]})
    assert find_leaks(body, secrets_of(index, ACTIVE))
    body = json.loads(bodies[0][1])
    cube = action["objects"]["cube"]["pos"]
    body["messages"][-1]["content"][0]["text"] += f" the cube sits at {cube}"
    assert {leak.kind for leak in find_leaks(body, secrets_of(index, ACTIVE))} == {"value"}


def test_the_rubric_prompt_is_clean():
    assert find_leaks({"system": system_prompt(), "messages": []}) == []


def test_judgments_are_written_as_annotators_and_feed_the_agreement_table(run, capsys):
    assert main(["judge", str(run), "--model", "local", "--judges", "3"]) == 0
    assert "6 episode judgments by 3 judge(s) of local" in capsys.readouterr().out
    store = AnnotationStore(RunIndex.load(run))
    state = store.state()
    for k in (1, 2, 3):
        name = f"judge-local-{k}"
        assert store.path(name).is_file()
        for episode in (ACTIVE, PASSIVE):
            items = {i for (e, a, i) in state if e == episode and a == name}
            assert set(GATE_CODES) <= items
            assert {"TL", "SR", "MS", "MP", "FG"} <= items <= set(GATE_CODES + CRITERION_CODES)
    sources = {json.loads(line)["source"] for line in store.path("judge-local-1").open()}
    assert sources == {"judge:local"}
    data = report_diagnostics.load(run)
    rows = {r[1]: r for r in report_diagnostics.agreement_section(data).tables[0].rows}
    assert rows["TL"][2] == "2" and rows["All criteria"][2] != "0"
    # a second run judges nothing again
    assert main(["judge", str(run), "--model", "local"]) == 0
    assert "6 already judged" in capsys.readouterr().out


def test_the_report_carries_the_diagnostics(run):
    from vabench.report import generate

    assert main(["judge", str(run), "--model", "local", "--judges", "3"]) == 0
    out = generate(run)
    names = {p.name for p in out.files}
    assert {"diagnostics.md", "agreement.md", "vote_rules.md", "agreement.csv"} <= names
    report = (run / "report" / "report.md").read_text()
    assert "## Inter-annotator agreement" in report and "| SPU | TL | 2 |" in report
    html = (run / "report" / "report.html").read_text()
    assert "Vote-rule sensitivity" in html and "Gwet AC1" in html
