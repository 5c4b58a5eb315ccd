"""The sweep's learning stage over real HTTP: a summary is learned once per (model, family) and
reused for every seed, run and track; `own`, `shared:<model>` and `none` show whose summary
each observation carries; a failed session is run again up to three attempts, each recorded,
and then final, an infrastructure failure is retried and is no attempt; a stopped sweep goes
on from its attempts and never learns a stored or finished summary again; the records and the
report say which summary each episode read."""

from __future__ import annotations

import asyncio
import json
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
import yaml
from engine_util import FAST_RETRY, reply, tool

from vabench import protocol as P
from vabench.agent.learning import LearningResult, read_result, write_result
from vabench.agent.learning_stage import LEARNING_ATTEMPTS, SummaryRecordError, SummaryStage
from vabench.config import load_config
from vabench.config.choices import choose
from vabench.demos.store import default_cache
from vabench.llm_pool.apis.base import IncomingRequest
from vabench.llm_pool.policies import PolicyError
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.report import make_report
from vabench.report.spend import bill
from vabench.run_layout import RunDir
from vabench.sweep.plan import plan
from vabench.sweep.runner import LocalSweep
from vabench.tasks import get_task

TASK = "grasp_single_cube"
LEARNING_CALLS = 3  # the stand-in learner: retrieve, frame, learn


def sweep_doc(server: LocalServer, models: list[str], **fields: Any) -> dict[str, Any]:
    doc = {
        "name": "t",
        "models": [
            server.endpoint_config(m, "openai_chat", model=m, retry={"max_attempts": 1})
            for m in models
        ],
        "tracks": ["active"],
        "tasks": [TASK],
        "seeds": [1000],
        "runs": 1,
        "step_budget": 1,
        "simulator": {"backend": "c"},
        "render": {"width": 64, "height": 48, "workers": 1},
        "executor": {"max_episodes": 64},
        "retries": {"infrastructure_rounds": 1},
    }
    return doc | fields


async def run_sweep(doc: dict[str, Any], tmp_path: Path, out: Path) -> LocalSweep:
    path = tmp_path / "sweep.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    config = load_config(path, overrides={"out": str(out)})
    sweep = LocalSweep(config, plan(config), out, choose(config))
    await sweep.run()
    return sweep


def ledger_lines(out: Path) -> list[dict[str, Any]]:
    """The ledger's whole lines (`Ledger.records` keeps only each line's outcome)."""
    return [json.loads(x) for x in RunDir(out).results.read_text().splitlines()]


def requests(server: LocalServer) -> list[tuple[str, str, str]]:
    """(model, system text, last user text) of every captured request."""
    out = []
    assert server.bodies is not None
    for _, raw in server.bodies:
        body = json.loads(raw)
        system = next(m["content"] for m in body["messages"] if m["role"] == "system")
        last = [m for m in body["messages"] if m["role"] == "user"][-1]["content"]
        text = last if isinstance(last, str) else " ".join(p.get("text", "") for p in last)
        out.append((body["model"], system, text))
    return out


def learning_calls(server: LocalServer) -> Counter[str]:
    return Counter(m for m, system, _ in requests(server) if P.LEARNING_STAGE_MARK in system)


def learning_sessions(run_dir: Path) -> Counter[tuple[str, str]]:
    """learning_start events in every events.jsonl under summaries/, set-aside logs included."""
    found: Counter[tuple[str, str]] = Counter()
    for events in (run_dir / "summaries").rglob("events.jsonl"):
        for line in events.read_text().splitlines():
            event = json.loads(line)
            if event["type"] == "learning_start":
                found[(event["model"], event["task"])] += 1
    return found


def test_one_learning_per_model_and_family_for_three_runs_of_twenty_seeds(tmp_path):
    async def main() -> None:
        config = ServerConfig(
            model_policies={
                "m1": {"policy": "conversation_hash"},
                "m2": {"policy": "random_action"},
            }
        )
        async with LocalServer(config, capture_bodies=True) as server:
            doc = sweep_doc(server, ["m1", "m2"], seeds="verified", runs=3)
            out = tmp_path / "out"
            sweep = await run_sweep(doc, tmp_path, out)
            assert len(sweep.ledger.records) == 2 * 20 * 3
            assert learning_sessions(out) == {("m1", TASK): 1, ("m2", TASK): 1}
            assert learning_calls(server) == {"m1": LEARNING_CALLS, "m2": LEARNING_CALLS}
            texts = {
                m: read_result(RunDir(out).summary(m, TASK)).summary_text for m in ("m1", "m2")
            }
            assert all(texts.values())
            # every evaluation request of a model carries that model's own summary
            evaluation = [(m, t) for m, s, t in requests(server) if P.LEARNING_STAGE_MARK not in s]
            assert len(evaluation) == 2 * 20 * 3
            assert all(texts[m] in t for m, t in evaluation)
            for record in ledger_lines(out):
                model = record["model"]
                assert (record["summary_mode"], record["summary_from"]) == ("own", model)
                assert record["summary_status"] == "learned"
            # a resumed sweep runs nothing and learns nothing again
            again = await run_sweep(doc, tmp_path, out)
            assert again.ledger.records == sweep.ledger.records
            assert again.summaries.sessions == 0
            assert learning_calls(server) == {"m1": LEARNING_CALLS, "m2": LEARNING_CALLS}

    asyncio.run(main())


def test_own_shared_and_none_tracks_show_whose_summary(tmp_path):
    async def main() -> None:
        config = ServerConfig(
            model_policies={
                "m1": {"policy": "conversation_hash"},
                "m2": {"policy": "random_action"},
            }
        )
        async with LocalServer(config, capture_bodies=True) as server:
            tracks = [
                "active",
                {"name": "active_shared", "protocol": "active", "summaries": "shared:m1"},
                {"name": "active_none", "protocol": "active", "summaries": "none"},
            ]
            out = tmp_path / "out"
            await run_sweep(sweep_doc(server, ["m1", "m2"], tracks=tracks), tmp_path, out)
            records = {(r["model"], r["track"]): r for r in ledger_lines(out)}
            text = {m: read_result(RunDir(out).summary(m, TASK)).summary_text for m in ("m1", "m2")}
            assert text["m1"] and text["m2"] and text["m1"] != text["m2"]
            expected = {
                ("m1", "active"): ("own", "m1", "learned"),
                ("m2", "active"): ("own", "m2", "learned"),
                ("m1", "active_shared"): ("shared:m1", "m1", "learned"),
                ("m2", "active_shared"): ("shared:m1", "m1", "learned"),
                ("m1", "active_none"): ("none", None, "none"),
                ("m2", "active_none"): ("none", None, "none"),
            }
            got = {
                k: (r["summary_mode"], r["summary_from"], r["summary_status"])
                for k, r in records.items()
            }
            assert got == expected
            assert learning_sessions(out) == {("m1", TASK): 1, ("m2", TASK): 1}
            shown = [(m, t) for m, s, t in requests(server) if P.LEARNING_STAGE_MARK not in s]
            assert len(shown) == 6
            # m2: its own summary on `active`, m1's on `active_shared`, none on `active_none`
            m2 = [t for m, t in shown if m == "m2"]
            assert sum(text["m2"] in t for t in m2) == 1 and sum(text["m1"] in t for t in m2) == 1
            # the `none` track's requests carry no summary section at all (docs/PROTOCOL.md)
            assert sum("Demonstration summary" not in t for _, t in shown) == 2
            make_report(out)
            assert "Summary source" in (out / "report" / "report.md").read_text()

    asyncio.run(main())


def test_a_failed_session_is_tried_three_times_and_an_infrastructure_failure_is_retried(tmp_path):
    async def main() -> None:
        # m1 answers the learning stage with text that is no decision: every attempt fails;
        # m2's server errors on every call: its session never ends in a stored result.
        config = ServerConfig(
            model_policies={"m1": {"policy": "echo"}, "m2": {"policy": "random_action"}},
        )
        # (A server that answers 503 on every call: nothing listening at all would stop the
        # sweep, as an endpoint that never answered does.)
        failing = ServerConfig(faults={"rates": {"unavailable": 1.0}})
        async with (
            LocalServer(config, capture_bodies=True) as server,
            LocalServer(failing) as down,
        ):
            doc = sweep_doc(server, ["m1", "m2"], seeds={"verified": 3})
            doc["models"][1]["base_url"] = down.base_url("openai_chat")
            out = tmp_path / "out"
            sweep = await run_sweep(doc, tmp_path, out)
            failed = read_result(RunDir(out).summary("m1", TASK))
            assert failed.status == "failed" and failed.stop_reason == "invalid_output"
            assert LEARNING_ATTEMPTS == 3 and failed.attempt == 3
            earlier = failed.earlier_attempts
            assert [(r.attempt, r.status, r.model_calls) for r in earlier] == [
                (1, "failed", 3),
                (2, "failed", 3),
            ]
            # each attempt's own records: set aside in order, the last one in place
            session = RunDir(out).learning_session("m1", TASK)
            for n in (1, 2):
                aside = read_result(session.path / f"attempt_{n}" / "learning.json")
                assert aside.attempt == n and aside.status == "failed"
                assert (session.path / f"attempt_{n}" / "events.jsonl").exists()
            assert read_result(session.learning_result).attempt == 3
            assert not (session.path / "attempt_3").exists()
            # the bill counts every attempt's calls once: 3 sessions of 3 calls
            learning = [r for r in bill(out).rows if r.source == "learning sessions"]
            assert {r.model: r.items for r in learning}["m1"] == 3
            assert not RunDir(out).summary("m2", TASK).exists()
            assert len(sweep.ledger.records) == 2 * 3
            records = {r["model"]: r for r in ledger_lines(out)}  # any one per model
            assert (
                records["m1"]["summary_status"] == "failed"
                and records["m1"]["summary_from"] is None
            )
            assert records["m2"]["status"] == "infrastructure_error"
            assert "learning stage" in records["m2"]["error"]
            # each round tried m2's session once, not once per episode waiting for it (3), and
            # an infrastructure failure is no attempt
            assert learning_sessions(out)[("m2", TASK)] == 2
            assert not list(RunDir(out).learning_session("m2", TASK).path.glob("attempt_*"))
            assert learning_sessions(out)[("m1", TASK)] == 3
            assert learning_calls(server)["m1"] == 3 * 3

    asyncio.run(main())


def test_a_task_with_atomic_demonstrations_learns_from_all_of_them_in_one_index():
    """The basket's form (FACTS): its four atomic videos, titled by their instructions, one
    frame index; a held-out variant gets its base family's video."""
    from dataclasses import replace

    from vabench.agent.learning_stage import load_demo_frames
    from vabench.demos import load_demo
    from vabench.demos.store import default_cache
    from vabench.tasks import BASKET_DEMONSTRATIONS, get_task

    composite = replace(get_task(TASK), name="composite", demonstrations=BASKET_DEMONSTRATIONS)
    demo = load_demo_frames(composite, default_cache())
    assert demo.composite and demo.scene is None  # single skills: no scene of the task
    videos = [load_demo(n) for n in BASKET_DEMONSTRATIONS]
    assert len(demo) == sum(v.n_frames for v in videos)
    starts = [0]
    for v in videos[:-1]:
        starts.append(starts[-1] + v.n_frames)
    titles = [get_task(n).instruction for n in BASKET_DEMONSTRATIONS]
    assert list(demo.videos) == list(zip(starts, titles, strict=True))
    assert demo.frames[starts[2]] == videos[2].frames[0]
    assert demo.index_entry(starts[3] + 1)["video"] == 4
    variant = replace(get_task(TASK), name="variant", base_family=TASK)
    base = load_demo_frames(variant, default_cache())
    assert base.frames == tuple(load_demo(TASK).frames)
    assert base.scene is not None and base.scene.image == base.frames[0]
    assert f"Task instruction: {get_task(TASK).instruction}" in base.scene.text


def test_a_held_out_variant_reads_its_base_familys_summary(tmp_path):
    async def main() -> None:
        config = ServerConfig(model_policies={"m1": {"policy": "conversation_hash"}})
        async with LocalServer(config, capture_bodies=True) as server:
            doc = sweep_doc(server, ["m1"], tracks=["active", "transfer"], seeds={"verified": 1})
            out = tmp_path / "out"
            await run_sweep(doc, tmp_path, out)
            tasks = {r["task"]: r for r in ledger_lines(out)}
            assert set(tasks) == {TASK, f"{TASK}_heldout"}
            assert learning_sessions(out) == {("m1", TASK): 1}
            text = read_result(RunDir(out).summary("m1", TASK)).summary_text
            shown = [t for _, s, t in requests(server) if P.LEARNING_STAGE_MARK not in s]
            assert len(shown) == 2 and all(text in t for t in shown)
            assert tasks[f"{TASK}_heldout"]["summary_status"] == "learned"

    asyncio.run(main())


# -- attempts and resume, on the stage itself ------------------------------------------------------


class Steps:
    """Replies in order, one per request; an int answers that HTTP status instead."""

    def __init__(self, steps: list[str | int]):
        self.steps = steps
        self.served = 0

    async def respond(self, request: IncomingRequest) -> str:
        step = self.steps[self.served]
        self.served += 1
        if isinstance(step, int):
            raise PolicyError("scripted outage", status=step)
        return step


JUNK = ["no json", "still none", "{"]  # an attempt that fails: three invalid replies
LEARN = [
    tool("expert.retrieve"),
    tool("expert.frame", steps=[0, 5, 10]),
    reply(
        {
            "tool": "expert.learn",
            "args": {
                "grasp_object_part": "the cube",
                "grasp_region": "two opposite side faces",
                "grasp_height_or_depth": "mid-height",
                "finger_placement": "one finger on each side face",
                "approach_strategy": "from above, then straight down",
                "posture_or_rotation": "fingers vertical, jaws parallel to the faces",
                "pre_close_checks": ["the cube sits between the fingers"],
                "test_lift_rule": "lift well clear of the table right after closing",
            },
        }
    ),
]


def test_attempts_survive_a_stopped_sweep_and_nothing_learned_is_learned_again(tmp_path):
    task = get_task(TASK)
    run_dir = tmp_path / "run"
    files = RunDir(run_dir)
    session = files.learning_session("m1", TASK)
    stored = files.summary("m1", TASK)
    policy = Steps([*JUNK, 503, *LEARN])

    async def main() -> None:
        async with LocalServer(policy=policy) as server:
            retry = {**FAST_RETRY, "max_attempts": 1}
            endpoint = server.endpoint_config("m1", "openai_chat", retry=retry)
            async with LLMPool([endpoint]) as llm:

                def stage() -> SummaryStage:
                    return SummaryStage(run_dir, llm, demo_cache=default_cache())

                # attempt 1 fails, then the provider fails: not stored, no attempt spent
                first = stage()
                r = await first.result("m1", task)
                assert (r.status, r.attempt, first.sessions) == ("infrastructure_error", 2, 2)
                assert [e.stop_reason for e in r.earlier_attempts] == ["invalid_output"]
                assert not stored.exists()
                # the next invocation goes on with attempt 2, from the attempt set aside
                second = stage()
                r = await second.result("m1", task)
                assert (r.status, r.attempt, second.sessions) == ("learned", 2, 1)
                assert [(e.attempt, e.status) for e in r.earlier_attempts] == [(1, "failed")]
                assert read_result(stored) == r
                # a stored summary is never learned again
                third = stage()
                assert await third.result("m1", task) == r and third.sessions == 0
                # nor one whose session ended but was not stored yet (a stop in between)
                stored.unlink()
                fourth = stage()
                again = await fourth.result("m1", task)
                assert fourth.sessions == 0 and again.summary == r.summary
                assert again.attempt == 2 and stored.exists()

    asyncio.run(main())
    assert policy.served == len(JUNK) + 1 + len(LEARN)  # every model call made once
    assert read_result(session.path / "attempt_1" / "learning.json").status == "failed"
    assert not (session.path / "attempt_2").exists()
    # the outage's log was set aside as an interrupted one, not as an attempt
    assert (session.path / "partial_1" / "events.jsonl").exists()


def test_a_stored_record_of_an_unknown_version_stops_with_one_message(tmp_path):
    async def main() -> str:
        async with (
            LocalServer(policy=Steps([])) as server,
            LLMPool([server.endpoint_config("m1", "openai_chat")]) as llm,
        ):
            stage = SummaryStage(tmp_path, llm, demo_cache=default_cache())
            with pytest.raises(SummaryRecordError) as err:
                await stage.result("m1", get_task(TASK))
            return str(err.value)

    path = RunDir(tmp_path).summary("m1", TASK)
    path.parent.mkdir(parents=True)
    record = LearningResult(
        task=TASK, model="m1", label=TASK, status="failed", stop_reason="model_stop", n_frames=3
    )
    write_result(path, record)
    doc = json.loads(path.read_text())
    path.write_text(json.dumps({**doc, "v": 9}))
    message = asyncio.run(main())
    assert str(path) in message and "version 9" in message and "remove it" in message
