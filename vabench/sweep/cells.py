"""The sweep's plan cut into cells and chunks, which the driver (`driver.Driver`) hands out.

A cell is the planned episodes of one (model, track, task) not yet in the ledger
(`pending_cells`); `chunks` cuts cells into nearly equal pieces so that the last engines to
finish leave none idle; `bins` deals whole tasks over engines sharing one GPU. Both weigh an
episode by `episode_costs`: the seconds this machine measured an episode of its task, where it
has, since a step budget bounds an episode and says little of how long one takes. The sweep's
critical path (`critical_path_tasks`: the tasks whose episodes bound its wall time) is found
here too: by the driver for every engine of a dealt sweep (`dealt_choices`), else by each
`runner.LocalSweep` among its own tasks (`sweep_critical_path`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import statistics
from collections.abc import Callable, Iterable, Mapping, Sequence

from vabench.check.pace import KindPace, machine_paces, measured_seconds
from vabench.config import SweepConfig
from vabench.config.choices import Choices
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import Key, ledger_key
from vabench.tasks import REGISTRY

log = logging.getLogger(__name__)

Cell = tuple[str, str, str]
"""(model, track, task)."""

PROGRESS_EVERY_S = 10.0
"""Seconds between the driver's progress lines while no chunk ends."""
MIN_CHUNK = 10
"""The fewest episodes a cell is cut down to: each chunk pays its own start-up."""
CHUNKS_PER_WORKER = 3


def task_cost(config: SweepConfig, task: str) -> int:
    """A task's cost for dealing the plan: its step budget (1 for an unknown task: it fails)."""
    return config.budget(task) if task in REGISTRY else 1


def episode_costs(
    config: SweepConfig, tasks: Iterable[str], paces: Mapping[str, KindPace]
) -> dict[str, float]:
    """Each of `tasks`' cost of an episode for dealing the plan: its `measured_seconds`; a task
    none measured costs its step budget at the seconds a budget step the measured ones took;
    with none measured, every cost is the step budget (`task_cost`): one plan never mixes
    seconds and steps."""
    tasks = sorted(set(tasks))
    measured = measured_seconds(config, tasks, paces)
    if not measured:
        return {task: float(task_cost(config, task)) for task in tasks}
    per_step = sum(measured.values()) / sum(task_cost(config, t) for t in measured)
    return {task: measured.get(task, task_cost(config, task) * per_step) for task in tasks}


def dealing_line(config: SweepConfig, tasks: Iterable[str], paces: Mapping[str, KindPace]) -> str:
    """What the plan's chunks are weighed by, for the sweep's log."""
    tasks = set(tasks)
    measured = measured_seconds(config, tasks, paces)
    if not measured:
        return "chunks weighed by step budgets (no sweep of these model kinds measured here)"
    return (
        f"chunks weighed by the seconds an episode took in this machine's latest sweep "
        f"({len(measured)} of {len(tasks)} tasks measured; the rest at their step budget's share)"
    )


def dealing_costs(config: SweepConfig, cells: Iterable[Cell], label: str) -> dict[str, float]:
    """The `episode_costs` of the tasks of `cells` at this machine's paces (`machine_paces`),
    what they are weighed by logged once (`label: chunks weighed by ...`)."""
    tasks, paces = {task for _, _, task in cells}, machine_paces()
    log.info("%s: %s", label, dealing_line(config, tasks, paces))
    return episode_costs(config, tasks, paces)


def pending_cells(
    keys: Iterable[EpisodeKey], finished: Iterable[Key]
) -> dict[Cell, list[EpisodeKey]]:
    """The planned episodes without a ledger record by (model, track, task), in plan order."""
    done = set(finished)
    cells: dict[Cell, list[EpisodeKey]] = {}
    for k in keys:
        if ledger_key(k) not in done:
            cells.setdefault((k.model, k.track, k.task), []).append(k)
    return cells


def task_groups(cells: Mapping[Cell, list[EpisodeKey]]) -> dict[tuple[str], list[EpisodeKey]]:
    """The cells of each task merged, every model and track, in plan order, keyed (task,): with
    batched physics a chunk runs one simulator batch per task, and a GPU steps a large batch
    about as fast as a small one."""
    groups: dict[tuple[str], list[EpisodeKey]] = {}
    for (_, _, task), keys in cells.items():
        groups.setdefault((task,), []).extend(keys)
    return groups


def chunks(
    cells: Mapping[Cell, list[EpisodeKey]] | Mapping[tuple[str], list[EpisodeKey]],
    workers: int,
    cost: Callable[[str], float],
    per_worker: int = CHUNKS_PER_WORKER,
) -> list[tuple[str, list[EpisodeKey]]]:
    """The cells (or `task_groups`) cut into chunks of nearly equal size, at least `per_worker`
    per worker where the cells allow (never below `MIN_CHUNK` episodes), costliest first
    (`cost(task)`), so the workers finish close together; named after the cell (model/track/task
    or task), "... part i/n" when cut."""
    total = sum(len(v) for v in cells.values())
    size = max(MIN_CHUNK, math.ceil(total / (workers * per_worker)))
    out = []
    for cell, keys in cells.items():
        parts = math.ceil(len(keys) / size)
        step = math.ceil(len(keys) / parts)
        for i, start in enumerate(range(0, len(keys), step), 1):
            name = "/".join(cell) + (f" part {i}/{parts}" if parts > 1 else "")
            out.append((name, keys[start : start + step]))
    return sorted(out, key=lambda c: -len(c[1]) * cost(c[1][0].task))


def bins(
    groups: Mapping[tuple[str], list[EpisodeKey]],
    workers: int,
    cost: Callable[[str], float],
) -> list[tuple[str, list[EpisodeKey]]]:
    """The `task_groups` dealt whole into at most `workers` chunks of nearly equal cost
    (longest first, each to the cheapest chunk so far; cost = episodes x `cost(task)`), named
    after their tasks joined by '+': for engine processes sharing one GPU under CUDA MPS
    (`executor: processes`, batched physics), each stepping one batch per task of its chunk."""
    ranked = sorted(groups.items(), key=lambda kv: -len(kv[1]) * cost(kv[0][0]))
    n = max(1, min(workers, len(ranked)))
    loads = [0.0] * n
    members: list[list[tuple[tuple[str], list[EpisodeKey]]]] = [[] for _ in range(n)]
    for group, keys in ranked:
        i = loads.index(min(loads))
        loads[i] += len(keys) * cost(group[0])
        members[i].append((group, keys))
    dealt = sorted(
        (
            (load, "+".join(g[0] for g, _ in m), [k for _, keys in m for k in keys])
            for load, m in zip(loads, members, strict=True)
            if m
        ),
        key=lambda c: -c[0],
    )
    return [(name, keys) for _, name, keys in dealt]


# -- the critical path ------------------------------------------------------------------------
def critical_path_tasks(budgets: Mapping[str, int]) -> set[str]:
    """The tasks whose episodes bound a round's wall time: those of the largest step budget,
    when it is at least twice the median of the other tasks' (the basket's 250 steps against
    50: its episodes take several times the others' decisions and would finish last,
    docs/PERFORMANCE.md). The median, not the largest other: `configs/all.yaml` also gives
    place_cube_on_cube 200 steps, whose episodes still end in as few decisions as the base
    families'. Where budgets are alike, none: a priority for everyone is a priority for no
    one."""
    if not budgets:
        return set()
    top = max(budgets.values())
    others = [b for b in budgets.values() if b != top]
    if not others or top < 2 * statistics.median(others):
        return set()
    return {name for name, b in budgets.items() if b == top}


def sweep_critical_path(decided: Sequence[str] | None, budgets: Mapping[str, int]) -> set[str]:
    """The tasks of `budgets` (this process's) on the critical path: those the driver decided
    for the whole sweep (`ExecutorChoice.critical_path`, `dealt_choices`), else those
    `critical_path_tasks` finds among them."""
    if decided is None:
        return critical_path_tasks(budgets)
    return set(decided) & set(budgets)


def with_critical_path(choices: Choices, budgets: Mapping[str, int]) -> Choices:
    """`choices` with the whole sweep's critical path (`critical_path_tasks` over every task's
    step budget, `budgets`), for every engine: each chunk runs in a `LocalSweep` of its own
    tasks, and the basket's chunk, alone, would find nothing to stand out from."""
    critical = tuple(sorted(critical_path_tasks(budgets)))
    return dataclasses.replace(
        choices, executor=dataclasses.replace(choices.executor, critical_path=critical)
    )


def dealt_choices(config: SweepConfig, cells: Iterable[Cell], choices: Choices) -> Choices:
    """What the engines of a sweep dealt over several run on: with batched physics, `choices`
    with the critical path of every task of `cells` (`with_critical_path` of their
    `task_cost`); else `choices` as they are (each `LocalSweep` finds its own)."""
    if not choices.physics.batched:
        return choices
    return with_critical_path(choices, {task: task_cost(config, task) for _, _, task in cells})
