"""Sweep configs: valid files load and resolve; every kind of mistake is reported, all of them at
once, each naming the file and the field."""

from __future__ import annotations

import logging
import typing
from pathlib import Path

import pytest
import yaml

from vabench.config import EMBEDDED_PLACEHOLDER_URL, SweepConfigError, load_config
from vabench.config.schema import SimulatorOptions
from vabench.sim_mjx.backends import BACKENDS
from vabench.tasks import BASE_FAMILIES, BENCHMARK_FAMILIES, get_task
from vabench.tasks.manifests import verified_seeds

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
KEY = "sk-test-secret-0123456789"
MODEL = {"name": "m", "api": "openai_chat", "base_url": "http://127.0.0.1:9/v1"}


def write(tmp_path: Path, doc: dict | str, name: str = "sweep.yaml") -> Path:
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else yaml.safe_dump(doc, sort_keys=False))
    return path


def minimal(**fields) -> dict:
    return {"models": [MODEL], "tracks": ["active"], **fields}


def problems_of(path: Path, environ=None, **kwargs) -> list[str]:
    with pytest.raises(SweepConfigError) as info:
        load_config(path, environ={} if environ is None else environ, **kwargs)
    lines = str(info.value).splitlines()
    assert len(lines) == len(info.value.problems)
    assert all(line.startswith(f"error: {path}: ") for line in lines)
    return lines


# -- valid configs ------------------------------------------------------------------------------


def test_minimal_config_gets_the_documented_defaults(tmp_path):
    config = load_config(write(tmp_path, minimal(), "my-sweep.yaml"), environ={})
    assert config.name == "my-sweep"
    assert config.out == "runs/my-sweep"
    assert config.tasks == BASE_FAMILIES  # every base family is registered
    assert config.seeds == {t: tuple(verified_seeds(t)) for t in BASE_FAMILIES}
    assert config.runs == 3 and config.step_budget is None
    assert config.simulator.backend == "auto"
    assert config.simulator.window_s == 0.01
    assert (config.render.width, config.render.height, config.render.quality) == (1280, 960, 95)
    assert config.render.workers == 2 and config.render.platform == "auto"
    assert config.render.backend == "auto"
    assert config.executor.kind == "auto" and config.executor.max_tasks is None
    assert config.executor.max_episodes == 256 and config.executor.in_flight == "auto"
    assert config.executor.slots_per_task is None
    assert config.retries.infrastructure_rounds == 3
    assert config.embedded_models == ()


def test_seed_spellings_resolve(tmp_path):
    tasks = ["grasp_single_cube", "lift_pot"]
    first = load_config(write(tmp_path, minimal(tasks=tasks, seeds={"verified": 3})), environ={})
    assert first.seeds == {t: tuple(verified_seeds(t)[:3]) for t in tasks}
    listed = load_config(write(tmp_path, minimal(tasks=tasks, seeds=[7, 3])), environ={})
    assert listed.seeds == {"grasp_single_cube": (7, 3), "lift_pot": (7, 3)}
    per_task = {"lift_pot": [5], "grasp_single_cube": [1, 2]}
    mapped = load_config(write(tmp_path, minimal(tasks=tasks, seeds=per_task)), environ={})
    assert mapped.seeds == {"grasp_single_cube": (1, 2), "lift_pot": (5,)}
    assert mapped.tasks == tuple(tasks)  # the order written, not the mapping's


def test_key_variable_set_in_the_environment(tmp_path):
    path = write(tmp_path, minimal(models=[{**MODEL, "api_key_env": "VABENCH_TEST_KEY"}]))
    config = load_config(path, environ={"VABENCH_TEST_KEY": KEY})
    assert config.models[0].api_key_env == "VABENCH_TEST_KEY"


def test_embedded_models_and_their_endpoints(tmp_path):
    models = [
        {"name": "local", "api": "anthropic", "base_url": "embedded"},
        {"name": "chat", "api": "openai_chat", "base_url": "embedded"},
        MODEL,
    ]
    doc = minimal(models=models, embedded_server={"policy": "scripted", "latency": {"mean_s": 1}})
    config = load_config(write(tmp_path, doc), environ={})
    assert config.embedded_models == ("local", "chat")
    assert config.embedded_server.policy == "scripted"
    assert config.embedded_server.latency.mean_s == 1
    assert config.models[0].base_url == EMBEDDED_PLACEHOLDER_URL
    urls = [e.base_url for e in config.endpoints(lambda api: f"http://live/{api}")]
    assert urls == ["http://live/anthropic", "http://live/openai_chat", MODEL["base_url"]]


def test_shipped_configs_load_without_keys():
    full = load_config(CONFIGS / "all.yaml", environ={})
    assert full.track_names == ("active", "passive", "transfer", "long_horizon")
    assert full.runs == 3 and full.tasks == BASE_FAMILIES
    assert set(full.all_tasks) == set(BENCHMARK_FAMILIES)  # every suite's every family
    assert all(len(s) == 20 for s in full.seeds.values())
    assert [m.name for m in full.models] == ["reference-servo"]
    assert full.embedded_models == ("reference-servo",)
    assert full.embedded_server.policy == "reference_servo"
    assert full.models[0].api == "openai_chat"

    smoke = load_config(CONFIGS / "smoke.yaml", environ={})
    assert sorted(len(get_task(t).arms) for t in smoke.tasks) == [1, 2]
    assert smoke.track_names == ("active", "passive") and smoke.runs == 1
    assert all(len(s) == 1 for s in smoke.seeds.values())
    assert smoke.step_budget is None  # the tasks' own budgets: the agent needs 15-27 steps
    assert smoke.simulator.backend == "c"
    assert (smoke.render.width, smoke.render.height, smoke.render.workers) == (640, 480, 1)
    assert smoke.embedded_models == ("reference-servo",)
    assert smoke.embedded_server.policy == "reference_servo"


def test_step_budget_caps_but_never_raises_a_task_budget(tmp_path):
    tasks = ["grasp_single_cube", "place_cube_on_cube"]  # budgets 50 and 200
    config = load_config(write(tmp_path, minimal(tasks=tasks, step_budget=100)), environ={})
    assert [config.budget(t) for t in tasks] == [50, 100]


def test_slots_per_task_default_is_the_planned_episodes_capped(tmp_path):
    config = load_config(write(tmp_path, minimal(executor={"max_episodes": 40})), environ={})
    assert [config.executor.slots(n) for n in (1, 40, 120)] == [1, 40, 40]
    fixed = load_config(write(tmp_path, minimal(executor={"slots_per_task": 8})), environ={})
    assert [fixed.executor.slots(n) for n in (1, 120)] == [8, 8]


def test_document_reads_back_to_the_same_config(tmp_path):
    models = [{"name": "local", "api": "openai_chat", "base_url": "embedded"}, MODEL]
    doc = minimal(models=models, tasks=["lift_pot"], seeds={"verified": 2}, step_budget=4)
    config = load_config(write(tmp_path, doc), environ={})
    again = load_config(write(tmp_path, config.document(), "resolved.yaml"), environ={})
    assert again == config


@pytest.mark.parametrize(
    ("impl", "backend"),
    [("warp", "warp"), ("jax", "mjx"), ("auto", "warp")],  # impl auto: Warp where it runs
)
def test_the_old_physics_spelling_is_read_with_one_warning(tmp_path, caplog, impl, backend):
    """`backend: mjx, impl: warp` (before `backend: warp`) still loads, to the same config as
    the new spelling, with one warning that names the file, the field and what to write; the
    resolved config (a run directory's sweep.yaml) has the new spelling and loads silently."""
    path = write(tmp_path, minimal(simulator={"backend": "mjx", "impl": impl}), "old.yaml")
    with caplog.at_level(logging.INFO):
        config = load_config(path, environ={})
    (warning,) = [r for r in caplog.records if r.levelno >= logging.WARNING]
    text = warning.getMessage()
    assert text.startswith(f"{path}: simulator.impl is deprecated: write simulator: ")
    assert f"{{backend: {backend}}} instead of {{backend: mjx, impl: {impl}}}" in text
    new = write(tmp_path, minimal(simulator={"backend": backend}), "old.yaml")  # same stem
    caplog.clear()
    with caplog.at_level(logging.INFO):
        assert load_config(new, environ={}) == config
        assert "impl" not in config.document()["simulator"]
        load_config(write(tmp_path, config.document(), "resolved.yaml"), environ={})
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_an_impl_that_contradicts_the_backend_is_a_problem_of_that_field(tmp_path):
    (line,) = problems_of(write(tmp_path, minimal(simulator={"backend": "warp", "impl": "jax"})))
    assert "simulator.impl: impl jax contradicts backend warp" in line
    (line,) = problems_of(write(tmp_path, minimal(simulator={"backend": "mjx", "impl": "gpu"})))
    assert "simulator.impl: impl must be one of" in line and "'gpu'" in line


def test_the_schema_lists_the_spellings_the_backends_module_accepts():
    """The schema's `Literal` is the one place outside `sim_mjx.backends` that writes the
    backend names (tests/test_layers.py lets declarations be): it must be that module's list."""
    assert typing.get_args(SimulatorOptions.model_fields["backend"].annotation) == BACKENDS


def test_overrides_replace_values_before_checking(tmp_path):
    path = write(tmp_path, minimal(out="runs/a"))
    config = load_config(path, environ={}, overrides={"out": "elsewhere", "executor.kind": "ray"})
    assert config.out == "elsewhere" and config.executor.kind == "ray"
    lines = problems_of(path, overrides={"runs": 0})
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: runs: ")


# -- one problem each ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "doc,field,words",
    [
        (minimal(trakcs=["active"]), "trakcs", "did you mean 'tracks'"),
        (
            minimal(models=[{**MODEL, "limits": {"rmp": 5}}]),
            "models[0].limits.rmp",
            "did you mean 'rpm'",
        ),
        (minimal(render={"widht": 640}), "render.widht", "did you mean 'width'"),
        (minimal(runs="three"), "runs", "must be a whole number, got 'three'"),
        (minimal(runs=0), "runs", "must be at least 1, got 0"),
        (
            minimal(models=[{**MODEL, "limits": {"rpm": 0}}]),
            "models[0].limits.rpm",
            "must be more than 0",
        ),
        (minimal(tracks=["active", "pasive"]), "tracks[1]", "did you mean 'passive'"),
        (minimal(tracks=["active", "active"]), "tracks[1]", "duplicate track 'active'"),
        (
            minimal(tracks=[{"name": "active", "protocol": "passive"}]),
            "tracks[0].protocol",
            "built-in",
        ),
        (
            minimal(tracks=[{"name": "abl", "protocl": "active"}]),
            "tracks[0].protocl",
            "did you mean 'protocol'",
        ),
        (
            minimal(tracks=[{"name": "a b", "protocol": "active"}]),
            "tracks[0].name",
            "names a directory",
        ),
        (minimal(summaries="mine"), "summaries", "own, none, shared:<model>"),
        (minimal(summaries="shared:gtp"), "summaries", "unknown model 'gtp'"),
        (
            minimal(tracks=[{"name": "x", "summaries": "shared:nobody"}]),
            "tracks[0].summaries",
            "unknown model 'nobody'",
        ),
        (
            minimal(learning={"max_model_calls": 0}),
            "learning.max_model_calls",
            "must be at least 1",
        ),
        (minimal(tracks=["active", "active"]), "tracks[1]", "duplicate"),
        (minimal(tracks=[]), "tracks", "at least 1"),
        (minimal(models=[]), "models", "at least 1"),
        (
            minimal(simulator={"backend": "gpu"}),
            "simulator.backend",
            "'auto', 'warp', 'mjx' or 'c'",
        ),
        (minimal(render={"width": 4000}), "render.width", "must be at most 1280"),
        (
            minimal(executor={"kind": "k8s"}),
            "executor.kind",
            "'auto', 'local', 'processes' or 'ray'",
        ),
        (minimal(executor={"in_flight": 0}), "executor.in_flight", "'auto' or a whole number"),
        (minimal(executor={"in_flight": "many"}), "executor.in_flight", "got 'many'"),
        (minimal(executor={"address": "ray://h:1"}), "executor.address", "kind: ray"),
        (
            minimal(models=[MODEL, {**MODEL, "base_url": "http://x/v1"}]),
            "models[1].name",
            "duplicate of models[0]",
        ),
        (minimal(models=[{**MODEL, "name": "org/model"}]), "models[0].name", "directory"),
        (
            minimal(models=[{**MODEL, "generation": {"thinking_budget": 2048}}]),
            "models[0].generation.thinking_budget",
            "anthropic only",
        ),
        (
            minimal(embedded_server={"policy": "random_acton"}),
            "embedded_server.policy",
            "did you mean 'random_action'",
        ),
        (minimal(embedded_server={"latncy": {}}), "embedded_server.latncy", "'latency'"),
        (minimal(tasks=["grasp_cubee"]), "tasks[0]", "did you mean 'grasp_single_cube'"),
        (minimal(tasks=["lift_pot", "lift_pot"]), "tasks[1]", "duplicate"),
        (minimal(tasks="all"), "tasks", "'base' or a non-empty list"),
        (minimal(seeds="all"), "seeds", "expected 'verified', {verified: N}"),
        (minimal(seeds={"verified": 0}), "seeds.verified", ">= 1"),
        (
            minimal(tasks=["lift_pot"], seeds={"verified": 21}),
            "seeds.verified",
            "only 20 verified seeds",
        ),
        (minimal(seeds=[1000, -1]), "seeds[1]", "integer >= 0"),
        (minimal(seeds=[1000, "x"]), "seeds[1]", "integer >= 0"),
        (minimal(seeds=[1000, 1000]), "seeds[1]", "duplicate seed 1000"),
        (
            minimal(tasks=["lift_pot"], seeds={"lift_pot": [1], "lift_pott": [2]}),
            "seeds.lift_pott",
            "did you mean 'lift_pot'",
        ),
        (
            minimal(tasks=["lift_pot", "place_shoe"], seeds={"lift_pot": [1]}),
            "seeds",
            "no seeds for task 'place_shoe'",
        ),
    ],
)
def test_one_problem_names_file_and_field(tmp_path, doc, field, words):
    path = write(tmp_path, doc)
    lines = problems_of(path)
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"error: {path}: {field}: "), lines[0]
    assert words in lines[0]


def test_missing_key_variable_fails_at_load_without_leaking(tmp_path):
    path = write(tmp_path, minimal(models=[{**MODEL, "api_key_env": "OPENAI_API_KEY"}]))
    (line,) = problems_of(path, environ={"OTHER": KEY})
    unset = "environment variable OPENAI_API_KEY is not set"
    assert line == f"error: {path}: models[0].api_key_env: {unset}"
    (line,) = problems_of(path, environ={"OPENAI_API_KEY": ""})  # set but empty is not a key
    assert "OPENAI_API_KEY is not set" in line


def test_yaml_syntax_error_names_the_line(tmp_path):
    path = write(tmp_path, "tracks: [active\nruns: 3\nmodels: []\n")
    (line,) = problems_of(path)
    assert line.startswith(f"error: {path}: line 2, column ")
    assert "YAML syntax error" in line


def test_a_key_written_twice_is_an_error(tmp_path):
    path = write(tmp_path, "runs: 1\ntracks: [active]\nruns: 3\n")
    (line,) = problems_of(path)
    assert line.startswith(f"error: {path}: line 3, column 1: ") and "duplicate key 'runs'" in line


def test_not_a_mapping_and_unreadable_file(tmp_path):
    (line,) = problems_of(write(tmp_path, "- a\n- b\n"))
    assert "expected a mapping" in line
    (line,) = problems_of(tmp_path / "absent.yaml")
    assert "cannot read" in line


def test_every_problem_of_a_file_is_reported_at_once(tmp_path):
    doc = {
        "models": [
            {**MODEL, "api_key_env": "VABENCH_UNSET_KEY"},
            {**MODEL, "name": "b", "limits": {"rpm": -1}},
        ],
        "tracks": ["active", "pasive"],
        "tasks": ["grasp_single_cube", "grasp_cubee", "lift_pott"],
        "runs": "three",
        "render": {"qualty": 90},
    }
    lines = problems_of(write(tmp_path, doc))
    fields = [line.split(": ")[2] for line in lines]
    assert sorted(fields) == sorted(
        [
            "models[0].api_key_env",
            "models[1].limits.rpm",
            "tracks[1]",
            "tasks[1]",
            "tasks[2]",
            "runs",
            "render.qualty",
        ]
    )
    # reported in the order the file reads, section by section
    assert [f.split(".")[0].split("[")[0] for f in fields] == [
        "models",
        "models",
        "tracks",
        "tasks",
        "tasks",
        "runs",
        "render",
    ]


def test_tracks_resolve_protocol_suite_and_summary_mode_and_round_trip(tmp_path):
    second = {**MODEL, "name": "teacher"}
    path = write(
        tmp_path,
        minimal(
            models=[MODEL, second],
            tasks=["grasp_single_cube", "lift_pot"],
            seeds=[1000],
            summaries="none",
            tracks=[
                "active",
                {"name": "passive", "summaries": "own"},
                {"name": "active_shared", "protocol": "active", "summaries": "shared:teacher"},
            ],
        ),
    )
    config = load_config(path, environ={})
    active, passive, shared = config.tracks
    assert (active.protocol, active.suite, active.summaries) == ("active", "base", "none")
    assert (passive.protocol, passive.summaries) == ("passive", "own")
    assert (shared.protocol, shared.suite, shared.summaries) == ("active", "base", "shared:teacher")
    assert [t.summary_source("m") for t in config.tracks] == [None, "m", "teacher"]
    assert config.track_tasks("active_shared") == ("grasp_single_cube", "lift_pot")
    again = write(tmp_path, config.document(), "again.yaml")
    assert load_config(again, environ={}) == config.model_copy(update={"out": config.out})


def test_a_transfer_track_needs_a_selected_family_with_a_held_out_variant(tmp_path):
    path = write(tmp_path, minimal(tasks=["click_bell_right"], seeds=[1000], tracks=["transfer"]))
    (line,) = problems_of(path)
    assert "tracks[0]" in line
    assert "none of the selected tasks has a registered held-out variant" in line
