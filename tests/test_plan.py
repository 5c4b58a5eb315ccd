"""The sweep plan (complete, deterministic, in the documented order) and the dry-run estimate
(counts, calls, image tokens, cost arithmetic)."""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import math
from pathlib import Path

import pytest
import yaml

from vabench.agent.usage import Assumptions, Usage, cost, episode_usage
from vabench.config import SweepConfig, load_config
from vabench.llm_pool.config import Prices
from vabench.sweep.plan import (
    FIRST_RUN,
    EpisodeKey,
    estimate,
    format_estimate,
    learning_sessions,
    plan,
)

TASKS = ["lift_pot", "grasp_single_cube"]  # dual-arm first: the order written must be kept
SEEDS = {"lift_pot": [1003, 1002], "grasp_single_cube": [1000, 1001, 1007]}
MODELS = [
    {
        "name": "cheap",
        "api": "openai_chat",
        "base_url": "http://127.0.0.1:9/v1",
        "prices": {"input": 2.0, "cached_input": 0.5, "output": 10.0},
    },
    {"name": "free", "api": "anthropic", "base_url": "embedded"},
]


def small_config(tmp_path: Path, **fields) -> SweepConfig:
    doc = {
        "models": MODELS,
        "tracks": ["passive", "active"],
        "tasks": TASKS,
        "seeds": SEEDS,
        "runs": 2,
        "step_budget": 5,
        **fields,
    }
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(doc))
    return load_config(path, environ={})


def test_plan_is_complete_without_duplicates(tmp_path):
    config = small_config(tmp_path)
    keys = plan(config)
    expected = {
        EpisodeKey(m["name"], track, task, seed, run)
        for m in MODELS
        for track in ("active", "passive")
        for task in TASKS
        for seed in SEEDS[task]
        for run in (FIRST_RUN, FIRST_RUN + 1)
    }
    assert len(keys) == len(set(keys)) == len(expected) == 2 * 2 * (2 + 3) * 2
    assert set(keys) == expected


def test_plan_is_deterministic_and_in_the_documented_order(tmp_path):
    config = small_config(tmp_path)
    keys = plan(config)
    assert keys == plan(small_config(tmp_path))
    models = [m["name"] for m in MODELS]
    tracks = ["passive", "active"]

    def documented(k: EpisodeKey):  # task > model > track > run > seed, each as configured
        return (
            TASKS.index(k.task),
            models.index(k.model),
            tracks.index(k.track),
            k.run,
            SEEDS[k.task].index(k.seed),
        )

    assert keys == sorted(keys, key=documented)
    # one task's episodes are contiguous: a simulator batch fills before the next task starts
    assert [task for task, _ in itertools.groupby(k.task for k in keys)] == TASKS


def test_episode_key_paths_ids_and_order():
    key = EpisodeKey("gpt", "passive", "lift_pot", 1003, 2)
    assert key.rel_dir == "episodes/gpt/passive/lift_pot/seed_1003/run_2"
    assert key.as_id() == "gpt/passive/lift_pot/1003/2"
    assert key < EpisodeKey("gpt", "passive", "lift_pot", 1003, 3)
    assert key < EpisodeKey("gpt", "passive", "lift_pot", 1004, 1)
    assert {key, EpisodeKey("gpt", "passive", "lift_pot", 1003, 2)} == {key}
    with pytest.raises(dataclasses.FrozenInstanceError):
        key.seed = 1  # type: ignore[misc]


def test_estimate_counts(tmp_path):
    config = small_config(tmp_path)
    est = estimate(config, plan(config))
    assert est.episodes == 40
    assert est.by_model == {"cheap": 20, "free": 20}
    assert list(est.by_track.items()) == [("passive", 20), ("active", 20)]
    assert list(est.by_task.items()) == [("lift_pot", 16), ("grasp_single_cube", 24)]
    # a subset of the plan (a resumed sweep's remaining episodes) counts only itself
    part = [k for k in plan(config) if k.model == "cheap" and k.task == "lift_pot"]
    sub = estimate(config, part)
    assert sub.by_model == {"cheap": 8} and sub.by_task == {"lift_pot": 8}
    assert [m.model for m in sub.models] == ["cheap"]


def test_calls_follow_the_budget_and_the_repair_share():
    a = Assumptions()
    for track in ("active", "passive"):
        one = episode_usage("grasp_single_cube", track, 5, (320, 240), "openai_chat", a)
        assert one.calls == 5
        assert one.output_tokens == 5 * a.output_tokens
        more = episode_usage(
            "grasp_single_cube",
            track,
            5,
            (320, 240),
            "openai_chat",
            Assumptions(extra_call_share=0.5),
        )
        assert more.calls == 7.5
        assert more.input_tokens == pytest.approx(1.5 * one.input_tokens)
    # later steps carry the history: twice the steps cost more than twice the input
    ten = episode_usage("grasp_single_cube", "active", 10, (320, 240), "openai_chat", a)
    five = episode_usage("grasp_single_cube", "active", 5, (320, 240), "openai_chat", a)
    assert ten.input_tokens > 2 * five.input_tokens


@pytest.mark.parametrize(
    "api,per_image",
    [
        # OpenAI tiles: 1280x960 -> 1024x768 -> 2x2 tiles = 765; 320x240 -> 1 tile = 255
        ("openai_chat", 765 - 255),
        # Anthropic: 1280x960 is scaled to 1.15 MP -> 1534; 320x240 -> ceil(76800 / 750) = 103
        ("anthropic", 1534 - 103),
    ],
)
def test_image_tokens_follow_retention_and_the_api_rule(api, per_image):
    a = Assumptions()

    def diff(track: str) -> float:
        big = episode_usage("grasp_single_cube", track, 5, (1280, 960), api, a)
        small = episode_usage("grasp_single_cube", track, 5, (320, 240), api, a)
        return big.input_tokens - small.input_tokens

    # active: every call carries the current image only (docs/PROTOCOL.md)
    assert diff("active") == 5 * per_image
    # passive: every call carries the current five-view bundle only
    assert diff("passive") == 5 * 5 * per_image


def test_long_contexts_compact_and_each_compaction_is_a_call():
    huge = Assumptions(output_tokens=8000)  # ~8k tokens per step: the 80 % mark within 30 steps
    usage = episode_usage("grasp_single_cube", "active", 50, (320, 240), "openai_chat", huge)
    compactions = usage.calls - 50
    assert 1 <= compactions < 10
    assert usage.output_tokens == 50 * 8000 + compactions * huge.summary_tokens


def test_cost_arithmetic(tmp_path):
    usage = Usage(calls=10, input_tokens=3_000_000, output_tokens=200_000)
    prices = Prices(input=2.0, cached_input=0.5, output=10.0)
    assert cost(usage, prices, Assumptions()) == pytest.approx(3 * 2.0 + 0.2 * 10.0)
    half = Assumptions(cached_input_share=0.5)
    assert cost(usage, prices, half) == pytest.approx(1.5 * 2.0 + 1.5 * 0.5 + 0.2 * 10.0)
    no_cache_price = Prices(input=2.0, output=10.0)  # cached input falls back to the input price
    assert cost(usage, no_cache_price, half) == pytest.approx(3 * 2.0 + 0.2 * 10.0)

    config = small_config(tmp_path)
    keys = plan(config)
    est = estimate(config, keys)
    cheap, free = est.models
    assert (cheap.model, free.model) == ("cheap", "free")
    expected = Usage()
    for k in keys:
        if k.model == "cheap":
            expected += episode_usage(k.task, k.track, 5, (1280, 960), "openai_chat", Assumptions())
    assert cheap.usage == expected
    assert cheap.cost_usd == pytest.approx(
        (expected.input_tokens * 2.0 + expected.output_tokens * 10.0) / 1e6
    )
    assert free.cost_usd == 0.0 and free.usage.calls == 20 * 5
    assert est.cost_usd == pytest.approx(cheap.cost_usd)
    assert est.usage == cheap.usage + free.usage


def test_estimate_works_inside_a_running_event_loop(tmp_path):
    config = small_config(tmp_path, render={"width": 640, "height": 480})

    async def from_a_coroutine():
        return estimate(config, plan(config))

    assert asyncio.run(from_a_coroutine()).usage.calls == 40 * 5


def test_format_estimate_shows_counts_totals_and_assumptions(tmp_path):
    config = small_config(tmp_path)
    est = estimate(config, plan(config))
    text = format_estimate(est)
    assert "Planned episodes: 40" in text
    for name in ("cheap", "free", "passive", "active", "lift_pot", "grasp_single_cube"):
        assert name in text
    total = next(line for line in text.splitlines() if line.startswith("total"))
    assert total.split()[1:3] == ["40", f"{math.ceil(est.usage.calls):,}"]
    assert total.split()[-1] == f"{est.cost_usd:,.2f}"
    assert "150 output tokens per call" in text


def test_tracks_plan_their_own_tasks_and_learning_sessions_are_counted_once(tmp_path):
    tracks = [
        "active",
        "transfer",
        {"name": "active_shared", "protocol": "active", "summaries": "shared:cheap"},
        {"name": "passive_none", "protocol": "passive", "summaries": "none"},
    ]
    seeds = {**SEEDS, "grasp_single_cube_heldout": [1000]}
    config = small_config(tmp_path, tracks=tracks, seeds=seeds, runs=1)
    keys = plan(config)
    by_track = {t: {k.task for k in keys if k.track == t} for t in config.track_names}
    assert by_track["transfer"] == {"grasp_single_cube_heldout"}  # lift_pot has no variant
    assert by_track["active"] == by_track["passive_none"] == set(TASKS)
    # own: each model per family; shared: cheap's (already counted); none: nothing; the
    # held-out variant reads its base family's summary: no session of its own
    assert set(learning_sessions(config, keys)) == {
        (m, t) for m in ("cheap", "free") for t in TASKS
    }
    assert "Learning stage: 4 sessions" in format_estimate(estimate(config, keys))
