"""The task registry: one module per family, each exporting TASK."""

from __future__ import annotations

from vabench.tasks import empty, probe_cube
from vabench.tasks.base import Task

REGISTRY: dict[str, Task] = {t.name: t for t in (empty.TASK, probe_cube.TASK)}


def get_task(name: str) -> Task:
    try:
        return REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown task {name!r}; valid tasks: {sorted(REGISTRY)}") from None
