"""The sweep's learning stage over real HTTP: a summary is learned once per (model, family) and
reused for every seed, run and track; `own`, `shared:<model>` and `none` show whose summary
each observation carries; a failed session is final and recorded, an infrastructure failure
is retried; the records and the report say which summary each episode read."""

from __future__ import annotations

import asyncio
import json
from collections import Counter
from pathlib import Path
from typing import Any

import yaml

from vabench import protocol as P
from vabench.agent.learning import read_result
from vabench.config import load_config
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.report import make_report
from vabench.run_layout import RunDir
from vabench.sweep.choices import choose
from vabench.sweep.plan import plan
from vabench.sweep.runner import LocalSweep

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


def test_a_failed_session_is_final_and_an_infrastructure_failure_is_retried(tmp_path):
    async def main() -> None:
        # m1 answers the learning stage with text that is no decision: the session fails;
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
            assert not RunDir(out).summary("m2", TASK).exists()
            assert len(sweep.ledger.records) == 2 * 3
            records = {r["model"]: r for r in ledger_lines(out)}  # any one per model
            assert (
                records["m1"]["summary_status"] == "failed"
                and records["m1"]["summary_from"] is None
            )
            assert records["m2"]["status"] == "infrastructure_error"
            assert "learning stage" in records["m2"]["error"]
            # each round tried m2's session once, not once per episode waiting for it (3)
            assert learning_sessions(out)[("m2", TASK)] == 2
            assert learning_sessions(out)[("m1", TASK)] == 1

    asyncio.run(main())


def test_a_task_with_atomic_demonstrations_learns_from_all_of_them_in_one_index():
    """The basket's form (FACTS): its four atomic videos, titled by their instructions, one
    frame index; a held-out variant gets its base family's video."""
    from dataclasses import replace

    from vabench.demos import load_demo
    from vabench.demos.store import CACHE_DIR
    from vabench.sweep.summaries import load_demo_frames
    from vabench.tasks import BASKET_DEMONSTRATIONS, get_task

    composite = replace(get_task(TASK), name="composite", demonstrations=BASKET_DEMONSTRATIONS)
    demo = load_demo_frames(composite, CACHE_DIR)
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
    assert load_demo_frames(variant, CACHE_DIR).frames == tuple(load_demo(TASK).frames)


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
