"""The shared services the episodes of one task run on: the simulator batch, the renderer and
the model pool (`task_services` builds them), with the engine's settings."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

from vabench.agent.batching import BatchStats
from vabench.agent.conversation import ContextLimits
from vabench.agent.simulation import RenderService, SimService
from vabench.agent.spec import EpisodeSpec
from vabench.llm_pool.config import GenerationOptions
from vabench.llm_pool.pool import LLMPool
from vabench.render.backends import Renderer
from vabench.render.images import ImageSettings
from vabench.tasks.base import Task

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EngineSettings:
    limits: ContextLimits = field(default_factory=ContextLimits)
    generation: GenerationOptions | None = None


@dataclass
class TaskServices:
    """The shared services episodes of one task run on."""

    sim: SimService
    render: RenderService
    llm: LLMPool
    settings: EngineSettings = field(default_factory=EngineSettings)
    on_decision: Callable[[EpisodeSpec, float], None] | None = None
    """Told the wall time of every decision an episode completes (observation, model calls,
    action): the sweep sizes the episodes it keeps in flight from it (`tuning.inflight`)."""


@contextlib.asynccontextmanager
async def task_services(
    task: Task,
    n_slots: int,
    llm: LLMPool,
    render_pool: Renderer,
    *,
    backend: str = "mjx",
    image: ImageSettings | None = None,
    settings: EngineSettings | None = None,
    sim_window_s: float = 0.01,
    render_window_s: float = 0.005,
    on_decision: Callable[[EpisodeSpec, float], None] | None = None,
    **batch_kwargs: Any,
) -> AsyncIterator[TaskServices]:
    """The services for up to `n_slots` concurrent episodes of `task` (building the simulator
    batch, which compiles under MJX, runs off the event loop)."""
    sim = await asyncio.to_thread(
        functools.partial(
            SimService, task, n_slots, backend=backend, window_s=sim_window_s, **batch_kwargs
        )
    )
    # Warp physics and the Warp renderer on one GPU: images read the state on the device.
    shares = getattr(render_pool, "shares", None)
    source = sim.batch.batch if shares and shares(sim.batch.batch) else None
    render = RenderService(
        render_pool, task.name, image or ImageSettings(), window_s=render_window_s, source=source
    )
    try:
        yield TaskServices(sim, render, llm, settings or EngineSettings(), on_decision)
    finally:
        await render.close()
        await sim.close()
        log.info("%s: %s", task.name, stage_line(sim.stats, render.stats))


def stage_line(sim: BatchStats, render: BatchStats) -> str:
    """Where a task's services spent their time: simulator and renderer calls, the items they
    served at once, and the seconds inside them (the profile's per-stage figures)."""
    parts = []
    for name, s in (("physics", sim), ("images", render)):
        parts.append(
            f"{name} {s.calls} calls, {s.items} items ({s.mean_batch:.1f} a call, at most "
            f"{s.max_batch}), {s.busy_s:.1f} s busy"
        )
    return "; ".join(parts)
