"""Registry-wide task tests: the 14 families, their budgets, manifests and experts; the reset
gate; checkpoints; model variants per slot; the task, replay and seeds CLIs."""

from __future__ import annotations

import dataclasses
import importlib
import json
import os
import pkgutil
import subprocess
import sys

import numpy as np
import pytest

from tests.expert_runs import expert_episodes
from vabench import tasks
from vabench.sim_mjx import scene
from vabench.tasks import BASE_FAMILIES, BENCHMARK_FAMILIES, REGISTRY, SUITES, families, get_task
from vabench.tasks.manifests import load_manifest
from vabench.tasks.task_batch import TaskBatch

# FACTS.md, "Tasks, budgets, evaluation seeds" (transcribed independently of the modules).
PAPER_BUDGETS = {
    "grasp_single_cube": (("right",), 50),
    "grasp_single_pen": (("right",), 50),
    "grasp_single_bottle": (("right",), 50),
    "grasp_single_bottle_upright": (("right",), 50),
    "grasp_pen_leaning_cube": (("right",), 50),
    "click_bell_right": (("right",), 50),
    "beat_block_hammer_right": (("right",), 100),
    "place_cube_in_bowl": (("right",), 50),
    "place_single_cube": (("right",), 100),
    "place_single_bottle_upright": (("right",), 100),
    "place_cube_on_cube": (("right",), 200),
    "lift_pot": (("left", "right"), 50),
    "place_shoe": (("left", "right"), 100),
    "handover_horizontal_block": (("left", "right"), 100),
}
PAPER_MODEL_IDS = {"click_bell_right": 2, "lift_pot": 2, "place_shoe": 10}

PRESENT = [n for n in BENCHMARK_FAMILIES if n in REGISTRY]
"""Every benchmark family with a module: the 14 base families, and the transfer variants and
the basket task as they land (their own budgets are checked below)."""
BASKET_BUDGET = 250  # five placements at place_cube_in_bowl's 50 each (our choice; see module)


def test_all_fourteen_families_are_registered():
    assert set(PAPER_BUDGETS) == set(BASE_FAMILIES)
    missing = [n for n in BASE_FAMILIES if n not in REGISTRY]
    assert not missing, f"families without a module: {missing}"


def test_the_registry_is_the_families_folder_and_nothing_else():
    """Each module of tasks/families/ is one family named as its file; the machinery beside the
    folder exports no TASK (so nothing needs a list of modules that are not tasks)."""
    in_folder = [m.name for m in pkgutil.iter_modules(families.__path__)]
    assert sorted(REGISTRY) == sorted(in_folder)
    for name in in_folder:
        assert importlib.import_module(f"vabench.tasks.families.{name}").TASK is REGISTRY[name]
    beside = [m.name for m in pkgutil.iter_modules(tasks.__path__) if m.name != "families"]
    assert beside and "task_batch" in beside
    for name in beside:
        assert not hasattr(importlib.import_module(f"vabench.tasks.{name}"), "TASK"), name
    benchmark = [n for n in REGISTRY if n in BENCHMARK_FAMILIES]
    assert list(REGISTRY)[: len(benchmark)] == [n for n in BENCHMARK_FAMILIES if n in REGISTRY]
    assert list(REGISTRY)[len(benchmark) :] == sorted(set(REGISTRY) - set(BENCHMARK_FAMILIES))


@pytest.mark.parametrize(
    ("files", "error", "match"),
    [
        ({"not_a_family": "X = 1\n"}, TypeError, "exports no TASK"),
        (
            {f"twin_{i}": "from vabench.tasks.families.empty import TASK\n" for i in (1, 2)},
            ValueError,
            "'empty' is taken twice",
        ),
    ],
)
def test_discovery_refuses_a_stray_module_in_the_families_folder(
    tmp_path, monkeypatch, files, error, match
):
    for name, text in files.items():
        (tmp_path / f"{name}.py").write_text(text)
    monkeypatch.setattr(families, "__path__", [str(tmp_path)])
    try:
        with pytest.raises(error, match=match):
            tasks._discover()
    finally:
        for name in files:
            sys.modules.pop(f"vabench.tasks.families.{name}", None)


@pytest.mark.parametrize("name", PRESENT)
def test_arms_budget_checkpoints_model_ids(name):
    task = get_task(name)
    suite = next(s for s, names in SUITES.items() if name in names)
    assert task.suite == suite and task.instruction
    if suite == "base":
        arms, budget = PAPER_BUDGETS[name]
        assert len(task.variants) == PAPER_MODEL_IDS.get(name, 1)
        assert task.base_family is None and task.demo_families == (name,)
    elif suite == "transfer":
        # a variant keeps its base family's instruction, arms and budget and reads its summary
        base = name.removesuffix("_heldout")
        assert task.base_family == base and task.summary_family == base
        assert task.instruction == get_task(base).instruction
        arms, budget = PAPER_BUDGETS[base]
    else:
        arms, budget = ("right",), BASKET_BUDGET
        assert len(task.demo_families) == 4 and task.summary_family == name
    assert (task.arms, task.step_budget) == (arms, budget)
    assert task.checkpoints[-1] == "completed" and len(set(task.checkpoints)) == len(
        task.checkpoints
    )


@pytest.mark.parametrize("name", PRESENT)
def test_sampling_is_deterministic_and_varies(name):
    task = get_task(name)
    a, b, c = task.sample(1234), task.sample(1234), task.sample(1235)
    assert a.variant == b.variant and a.params == b.params
    for obj, (pos, quat) in a.poses.items():
        np.testing.assert_array_equal(pos, b.poses[obj][0])
        np.testing.assert_array_equal(quat, b.poses[obj][1])
    assert any(not np.allclose(a.poses[o][0], c.poses[o][0]) for o in a.poses)


@pytest.mark.parametrize("name", PRESENT)
def test_variants_share_structure_and_objects(name):
    task = get_task(name)
    models = task.build_models()
    names = [scene.free_objects(m) for m in models]
    assert all(n == names[0] for n in names)
    assert set(task.sample(1000).poses) <= {n for n, _ in names[0]}


@pytest.mark.parametrize("name", PRESENT)
def test_manifest_holds_twenty_verified_seeds(name):
    doc = load_manifest(name)
    seeds = doc["retained"]
    assert len(seeds) == 20 and len(set(seeds)) == 20 and seeds == sorted(seeds)
    assert min(seeds) >= 1000 and doc["probed"] >= 20
    # every candidate up to the last retained one was probed: retained or rejected with a reason
    probed = set(range(1000, 1000 + doc["probed"]))
    assert set(seeds) | {int(s) for s in doc["rejected"]} == probed
    assert all(doc["rejected"].values())


def _expert_check(name: str, seeds: list[int]) -> None:
    task = get_task(name)
    for ep in expert_episodes(name, seeds):  # the family file's own test checks these too
        assert ep.success, (name, ep.seed, ep.end)
        assert ep.steps <= task.step_budget
        progress = [a["progress"] for a in ep.actions]
        assert progress == sorted(progress), (name, ep.seed, progress)
        assert progress[-1] == len(task.checkpoints)
        assert all(a["valid"] for a in ep.actions)  # experts speak the model's protocol
        assert [a["success"] for a in ep.actions].index(True) == len(ep.actions) - 1


@pytest.mark.parametrize("name", PRESENT)
def test_expert_solves_first_two_verified_seeds(name):
    """Default run: 2 verified seeds per family through the batch (C MuJoCo backend)."""
    _expert_check(name, load_manifest(name)["retained"][:2])


@pytest.mark.slow
@pytest.mark.parametrize("name", PRESENT)
def test_expert_solves_all_verified_seeds(name):
    _expert_check(name, load_manifest(name)["retained"])


def test_reset_gate_rejects_an_object_still_turning():
    """A cube dropped tilted from 10 cm with no time to settle turns in the observed window."""
    base = get_task("probe_cube")

    @dataclasses.dataclass(frozen=True)
    class Tumbling(type(base)):  # type: ignore[misc]
        def sample(self, seed):
            s = base.sample(seed)
            pos, _ = s.poses["cube"]
            tilt = np.array([np.cos(0.4), np.sin(0.4), 0.0, 0.0])
            return dataclasses.replace(s, poses={"cube": (pos + [0, 0, 0.10], tilt)})

    task = Tumbling(**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)})
    task = dataclasses.replace(task, settle_steps=0, observe_steps=200)
    tb = TaskBatch(task, 1, backend="c")
    rep = tb.reset([0], [3])[0]
    assert rep.finite and not rep.ok and "turned" in rep.reason
    ok = TaskBatch(base, 1, backend="c").reset([0], [3])[0]
    assert ok.ok and ok.reason is None


def test_idle_slots_keep_their_predicate_state():
    task = get_task("grasp_single_cube")
    tb = TaskBatch(task, 2, backend="c")
    tb.reset([0, 1], [1000, 1001])
    q1 = tb.batch.qpos()[1].copy()
    out = tb.step([{"action": "gripper.close"}, None])
    assert out[1] is None and tb.steps.tolist() == [1, 0]
    np.testing.assert_array_equal(tb.batch.qpos()[1], q1)


@pytest.mark.parametrize("backend", ["c", pytest.param("mjx", marks=pytest.mark.slow)])
def test_model_variants_are_per_slot(backend):
    """Two cube sizes in one batch: each slot rests at its own variant's height."""
    from vabench.sim_mjx.scene import add_free_box

    halves = (0.02, 0.03)
    models = [
        scene.build_model(
            ("right",), lambda s, h=h: add_free_box(s, "cube", [h] * 3, [1, 0, 0, 1], 0.1)
        )
        for h in halves
    ]
    if backend == "c":
        from vabench.sim_mjx.cpu import CpuBatch

        batch = CpuBatch(models, 2)
    else:
        from vabench.sim_mjx.mjx_batch import SimBatch

        batch = SimBatch(models, 2)
    q = scene.home_qpos(models[0])
    adr = dict(scene.free_objects(models[0]))["cube"]
    q[adr : adr + 3] = [0.2, -0.1, 0.80]
    batch.reset([0, 1], np.stack([q, q]), settle_steps=100, variants=[1, 0])
    z = batch.qpos()[:, adr + 2]
    np.testing.assert_allclose(z, [0.741 + halves[1], 0.741 + halves[0]], atol=1e-3)
    assert batch.variant().tolist() == [1, 0]
    with pytest.raises(ValueError, match="variants"):
        batch.reset([0], q[None], variants=[2])


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", *args],
        capture_output=True,
        text=True,
        timeout=600,
        env=os.environ.copy(),
    )


def test_tasks_cli_list_and_show():
    out = _run("vabench.tasks", "list", "--json")
    assert out.returncode == 0, out.stderr
    docs = {d["name"]: d for d in json.loads(out.stdout)}
    assert set(docs) == set(PRESENT)
    assert docs["place_single_cube"]["checkpoints"][-1] == "completed"
    out = _run("vabench.tasks", "show", "place_single_cube", "--seed", "1000", "--json")
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert doc["seed"] == 1000 and set(doc["objects"]) == {"cube", "pad"}
    assert len(doc["objects"]["cube"]["quat"]) == 4
    bad = _run("vabench.tasks", "show", "no_such_task", "--seed", "1")
    assert bad.returncode == 2 and "valid tasks" in bad.stderr


def test_replay_cli_runs_the_expert():
    out = _run(
        "vabench.replay",
        "--task",
        "place_single_cube",
        "--seed",
        "1000",
        "--expert",
        "--backend",
        "c",
        "--json",
    )
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert doc["success"] and doc["steps"][-1]["checkpoint"] == "completed"
    assert doc["steps"][-1]["checks"]["gripper_open"]


def test_seeds_cli_writes_a_manifest_and_the_yield_table(tmp_path):
    out = _run(
        "vabench.seeds", "verify", "--task", "grasp_single_cube", "--n", "2", "--out", str(tmp_path)
    )
    assert out.returncode == 0, out.stderr
    doc = json.loads((tmp_path / "grasp_single_cube.json").read_text())
    assert doc["retained"] == [1000, 1001] and doc["probed"] == 2
    assert "Yield (%)" in out.stdout and "grasp_single_cube" in out.stdout


def _mesh_model(box_half: float, mesh_radius: float):
    import mujoco

    return mujoco.MjModel.from_xml_string(f"""
<mujoco><asset>
<mesh name="c" builtin="cone" params="12 1" scale="{mesh_radius} {mesh_radius} 0.05"/></asset>
<worldbody><geom type="plane" size="1 1 0.1"/><body name="obj"><freejoint/>
<geom type="mesh" mesh="c" mass="0.1"/><geom type="box" size="{box_half} 0.035 0.02" pos="0 0 0.1"
mass="0.1"/></body></worldbody></mujoco>""")


def test_variants_accept_a_shared_mesh_and_refuse_a_different_one():
    from vabench.sim_mjx.variants import ModelVariants

    same = ModelVariants([_mesh_model(0.02, 0.03), _mesh_model(0.021, 0.03)])
    assert same.n == 2 and same.varying  # the box size differs per slot
    with pytest.raises(ValueError, match="differs"):
        ModelVariants([_mesh_model(0.02, 0.03), _mesh_model(0.02, 0.04)])
