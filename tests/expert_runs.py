"""Expert episodes through the batch (C MuJoCo), run once per test process for each family and
seed list: a family's own test file and tests/test_tasks.py check the same episodes, each with
its own assertions, instead of stepping the same physics twice. Episodes are read, never
changed, by the tests that share them."""

from __future__ import annotations

import functools
from collections.abc import Sequence

from vabench.tasks import get_task
from vabench.tasks.task_batch import ExpertEpisode, TaskBatch, run_experts


def expert_episodes(name: str, seeds: Sequence[int]) -> tuple[ExpertEpisode, ...]:
    """The expert of family `name` on `seeds`, one batch slot a seed (as `run_experts`)."""
    return _run(name, tuple(seeds))


@functools.cache
def _run(name: str, seeds: tuple[int, ...]) -> tuple[ExpertEpisode, ...]:
    tb = TaskBatch(get_task(name), len(seeds), backend="c")
    return tuple(run_experts(tb, list(seeds)))
