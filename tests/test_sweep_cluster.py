"""`executor: ray` on a three-node cluster (`ray.cluster_utils.Cluster`, all on this machine,
resources faked): one engine per node; a node killed mid-sweep costs only its unfinished
episodes, which run again elsewhere, and the sweep ends with every planned episode recorded
exactly once, by the driver alone.

The model is the embedded server's `conversation_hash` policy (an episode's decisions are a
function of its own conversation), with some latency so that episodes are in flight when the
node goes.
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from pathlib import Path

import pytest
import ray
from ray.cluster_utils import Cluster

from vabench.config import load_config
from vabench.config.choices import choose
from vabench.run_layout import RESULTS
from vabench.sweep.plan import plan
from vabench.sweep.ray_executor import run_ray

CONFIG = """\
name: cluster
models:
  - {name: local, api: openai_chat, base_url: embedded}
embedded_server: {policy: conversation_hash, latency: {mean_s: 0.4}, simulate_cache: false}
tracks: [active]
summaries: none
tasks: [grasp_single_cube, place_single_cube, grasp_single_pen]
seeds: {verified: 4}
runs: 1
step_budget: 3
simulator: {backend: c}
render: {width: 64, height: 48, workers: 1}
executor: {kind: ray, in_flight: 2}
"""
PLANNED = 3 * 4  # tasks x seeds


@pytest.fixture(scope="module")
def cluster():
    """A head and two workers, 2 CPUs each (one engine of 1 + render.workers CPUs on each)."""
    try:
        cluster = Cluster(
            initialize_head=True, head_node_args={"num_cpus": 2, "include_dashboard": False}
        )
        workers = [cluster.add_node(num_cpus=2) for _ in range(2)]
        ray.init(address=cluster.address)
        cluster.wait_for_nodes()
    except Exception as err:  # say why, never skip: this module is the cluster's test
        pytest.fail(f"a local Ray cluster does not start here: {type(err).__name__}: {err}")
    yield cluster, workers
    ray.shutdown()
    cluster.shutdown()


def ledger_keys(run_dir: Path) -> list[tuple]:
    path = run_dir / RESULTS
    if not path.exists():
        return []
    return [
        (r["model"], r["track"], r["task"], r["seed"], r["run"])
        for r in map(json.loads, path.read_text().splitlines())
    ]


def driver_lines(caplog, start: str) -> list[tuple]:
    """The arguments of the driver's log lines whose format starts with `start`."""
    return [
        r.args
        for r in caplog.records
        if r.name == "vabench.sweep.ray_executor" and r.msg.startswith(start)
    ]


def busy_engines(caplog) -> set[str]:
    """The nodes of the engines that were handed a chunk they have not finished."""
    nodes = {i: info["node"] for i, info in driver_lines(caplog, "ray: engine %d started")}
    given = {
        name: engine for name, _, engine in driver_lines(caplog, "ray: chunk %s (%d episodes)")
    }
    for name, *_ in driver_lines(caplog, "ray: chunk %s done on"):
        given.pop(name, None)
    busy = {int(re.match(r"engine (\d+)", engine).group(1)) for engine in given.values()}
    return {nodes[i] for i in busy if i in nodes}


def test_a_node_killed_mid_sweep_costs_only_its_unfinished_episodes(cluster, tmp_path, caplog):
    cluster, workers = cluster
    path = tmp_path / "cluster.yaml"
    path.write_text(CONFIG)
    run_dir = tmp_path / "out"
    config = load_config(path, overrides={"out": str(run_dir)})
    keys = plan(config)
    assert len(keys) == PLANNED
    run_dir.mkdir()
    (run_dir / "plan.json").write_text(json.dumps([k.as_id() for k in keys]))

    outcome: dict = {}

    def driver() -> None:
        try:
            outcome["records"] = run_ray(
                config,
                keys,
                run_dir,
                choose(config),
                on_engines=outcome.setdefault("engines", []).extend,
            )
        except BaseException as err:  # reported by the assertions below
            outcome["error"] = err

    with caplog.at_level(logging.INFO, logger="vabench.sweep.ray_executor"):
        thread = threading.Thread(target=driver, daemon=True)
        thread.start()
        # some episodes are done, and a worker node's engine is in the middle of a chunk: kill
        # that node
        deadline = time.monotonic() + 150
        while not (
            ledger_keys(run_dir) and any(w.node_id in busy_engines(caplog) for w in workers)
        ):
            assert thread.is_alive() and time.monotonic() < deadline, outcome
            time.sleep(0.1)
        victim = next(w for w in workers if w.node_id in busy_engines(caplog))
        recorded_at_kill = len(ledger_keys(run_dir))
        cluster.remove_node(victim)
        thread.join(timeout=240)
        assert not thread.is_alive(), "the sweep did not end"
    assert "error" not in outcome, outcome
    text = caplog.text
    assert recorded_at_kill < PLANNED
    assert "is gone" in text and "go back to the queue" in text, text[-3000:]
    assert " (again) done on " in text, text[-3000:]  # the lost episodes ran again elsewhere
    got = ledger_keys(run_dir)
    assert len(got) == len(set(got)) == PLANNED  # every episode exactly once
    assert (
        sorted(got)
        == sorted(outcome["records"])
        == sorted((k.model, k.track, k.task, k.seed, k.run) for k in keys)
    )
    assert not (run_dir / "results.duplicates.jsonl").exists()
    statuses = {json.loads(x)["status"] for x in (run_dir / RESULTS).read_text().splitlines()}
    assert statuses <= {"success", "failure"}
    # the driver's report of engine time: the dead engine's clock stopped at its death, the
    # one started in its place counted on its own, and the episodes add up
    report = outcome["engines"]
    dead = [r for r in report if r["died"]]
    assert len(dead) == 1 and len(report) == len(workers) + 2  # head, workers, replacement
    assert dead[0]["working_s"] > 0 and dead[0]["life_s"] < max(r["life_s"] for r in report)
    assert sum(r["episodes"] for r in report) == PLANNED
