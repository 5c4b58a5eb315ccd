"""The task registry: one module per family in `families/`, each exporting TASK.

`BASE_FAMILIES` lists the paper's 14 base families in the paper's order; `REGISTRY` holds the
TASK of every module in `families/` (the benchmark families plus development tasks such as
`empty` and `probe_cube`, whose `suite` is "dev"). Every module of that folder is a family, and
nothing outside it is: the machinery the families share (`base`, `common`, `expert`,
`grasp_place`, `heldout`, `objects`, the `skills_*` modules) and the machinery that runs them
(`task_batch`, `manifests`) sit beside the folder, so no list of exceptions is needed.
"""

from __future__ import annotations

import importlib
import pkgutil

from vabench.tasks import families
from vabench.tasks.base import Task

BASE_FAMILIES = (
    "grasp_single_cube",
    "grasp_single_pen",
    "grasp_single_bottle",
    "grasp_single_bottle_upright",
    "grasp_pen_leaning_cube",
    "click_bell_right",
    "beat_block_hammer_right",
    "place_cube_in_bowl",
    "place_cube_on_cube",
    "place_single_cube",
    "place_single_bottle_upright",
    "place_shoe",
    "handover_horizontal_block",
    "lift_pot",
)

TRANSFER_FAMILIES = (
    "grasp_single_bottle_heldout",
    "grasp_single_bottle_upright_heldout",
    "grasp_single_cube_heldout",
    "place_single_cube_heldout",
    "place_cube_in_bowl_heldout",
    "place_cube_on_cube_heldout",
    "place_single_bottle_upright_heldout",
)
"""The controlled-transfer track: seven held-out variants, each `<base>_heldout` (FACTS)."""
LONG_HORIZON_FAMILIES = ("put_everything_in_basket",)
"""The long-horizon track: the five-object basket task."""
BASKET_DEMONSTRATIONS = (
    "place_single_cube",
    "grasp_single_bottle",
    "grasp_single_bottle_upright",
    "grasp_single_pen",
)
"""The basket's four atomic videos (FACTS, "Demonstration protocol")."""
SUITES = {
    "base": BASE_FAMILIES,
    "transfer": TRANSFER_FAMILIES,
    "long_horizon": LONG_HORIZON_FAMILIES,
}
"""Benchmark families per suite, in the paper's order."""
BENCHMARK_FAMILIES = BASE_FAMILIES + TRANSFER_FAMILIES + LONG_HORIZON_FAMILIES


def _discover() -> dict[str, Task]:
    """The TASK of every module in `families/`, benchmark families in the paper's order first,
    then the others by name. A module without TASK, or a name taken twice, is a mistake in the
    folder and raises rather than being skipped."""
    found: dict[str, Task] = {}
    for info in pkgutil.iter_modules(families.__path__):
        module = importlib.import_module(f"{families.__name__}.{info.name}")
        task = getattr(module, "TASK", None)
        if not isinstance(task, Task):
            raise TypeError(f"{module.__name__} is in tasks/families/ but exports no TASK")
        if task.name in found:
            raise ValueError(f"{module.__name__}: task name {task.name!r} is taken twice")
        found[task.name] = task
    order = {name: i for i, name in enumerate(BENCHMARK_FAMILIES)}
    return dict(sorted(found.items(), key=lambda kv: (order.get(kv[0], len(order)), kv[0])))


REGISTRY: dict[str, Task] = _discover()


def get_task(name: str) -> Task:
    try:
        return REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown task {name!r}; valid tasks: {sorted(REGISTRY)}") from None


def base_tasks() -> list[Task]:
    """The base families present, in the paper's order."""
    return [REGISTRY[n] for n in BASE_FAMILIES if n in REGISTRY]


def benchmark_tasks(suite: str | None = None) -> list[Task]:
    """The benchmark families present (every suite but "dev", or one suite), in order."""
    names = BENCHMARK_FAMILIES if suite is None else SUITES[suite]
    return [REGISTRY[n] for n in names if n in REGISTRY]
