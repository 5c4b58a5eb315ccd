"""The simulator and the renderer as shared services of many concurrent episodes.

`SimService` owns one `TaskBatch` (every slot an episode of one task) and executes what the
episodes ask of it in batches: the resets and robot actions that arrive within a short window
go to the simulator together, resets first (one settle call), then the actions (one jitted
step over the whole batch, idle slots frozen). Everything that touches the batch runs on one
worker thread, one call at a time, and every answer carries a `SlotSnapshot` read in that same
call, so an episode never reads the batch while another call changes it.

`RenderService` does the same for images: the render items of every episode that asks within
the window go to the renderer as one request (`vabench.render.backends`: the GL worker
processes, or one pass of the Warp ray tracer on a GPU).

A snapshot holds both sides of the privilege boundary, kept apart by name: `proprio` is the
model-visible robot state (the fields of FACTS, via `proprio_fields`); `qpos`, `variant` and
`gcs` are evaluator-side inputs of the renderer and the camera and never reach a prompt.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from vabench.agent.batching import MicroBatcher
from vabench.render.backends import Renderer
from vabench.render.images import ImageSettings, RenderItem
from vabench.sim_mjx.layout import proprio_fields
from vabench.tasks.base import Task
from vabench.tasks.task_batch import SettleReport, StepOutcome, TaskBatch


@dataclass(frozen=True)
class SlotSnapshot:
    """One slot right after a reset or an action."""

    proprio: dict[str, dict[str, Any]]  # model-visible
    qpos: np.ndarray  # evaluator-side: for the renderer
    slot: int  # evaluator-side: where the renderer may read the state on the device
    variant: int  # evaluator-side: object model id
    gcs: dict[str, np.ndarray]  # evaluator-side: camera targets (GC per arm)
    progress: int  # checkpoints reached (evaluator-side)
    objects: dict[str, dict[str, list[float]]] | None = None
    """Evaluator-side object poses {name: {pos, quat (wxyz)}}, for the records only: the viewer's
    evaluator panel and the trajectory hints of the diagnostics read them."""


@dataclass(frozen=True)
class SimRequest:
    kind: Literal["reset", "act"]
    slot: int
    seed: int | None = None
    action: Any = None


@dataclass(frozen=True)
class SimReply:
    snapshot: SlotSnapshot
    report: SettleReport | None = None  # resets
    outcome: StepOutcome | None = None  # actions


@dataclass
class SimCounters:
    resets: int = 0
    reset_calls: int = 0
    actions: int = 0
    step_calls: int = 0  # jitted simulator calls for actions


class SimService:
    """Slots, resets and robot actions of one task's episodes over one simulator batch."""

    def __init__(
        self,
        task: Task,
        n_slots: int,
        *,
        backend: str = "mjx",
        window_s: float = 0.01,
        **batch_kwargs: Any,
    ):
        self.task = task
        self.batch = TaskBatch(task, n_slots, backend=backend, **batch_kwargs)
        self.n_slots = n_slots
        self.counters = SimCounters()
        self._free = list(range(n_slots))[::-1]
        self._batcher: MicroBatcher[SimRequest, SimReply] = MicroBatcher(
            self._run, window_s=window_s, max_batch=n_slots, name=f"sim-{task.name}"
        )

    # -- slots -----------------------------------------------------------------------------
    def acquire(self) -> int:
        if not self._free:
            raise RuntimeError(f"all {self.n_slots} slots of {self.task.name} are in use")
        return self._free.pop()

    def release(self, slot: int) -> None:
        if slot in self._free or not 0 <= slot < self.n_slots:
            raise ValueError(f"slot {slot} is not in use")
        self._free.append(slot)

    # -- requests --------------------------------------------------------------------------
    async def reset(self, slot: int, seed: int) -> SimReply:
        return await self._batcher.submit(SimRequest("reset", slot, seed=seed))

    async def act(self, slot: int, action: Any) -> SimReply:
        """Execute one robot action (a validated protocol model) in `slot`."""
        return await self._batcher.submit(SimRequest("act", slot, action=action))

    @property
    def stats(self):
        return self._batcher.stats

    async def close(self) -> None:
        """Finish the queued requests, then release the batch's threads or device memory at
        once (not when the collector gets to it: a sweep builds a batch per task)."""
        await self._batcher.close()
        await asyncio.to_thread(self.batch.batch.close)

    # -- the worker-thread side ------------------------------------------------------------
    def _run(self, requests: Sequence[SimRequest]) -> list[SimReply]:
        slots = [r.slot for r in requests]
        if len(set(slots)) != len(slots):
            raise RuntimeError(f"two requests for one slot in one batch: {sorted(slots)}")
        tb = self.batch
        resets = [r for r in requests if r.kind == "reset"]
        reports: dict[int, SettleReport] = {}
        if resets:
            got = tb.reset([r.slot for r in resets], [int(r.seed) for r in resets])  # type: ignore[arg-type]
            reports = {r.slot: rep for r, rep in zip(resets, got, strict=True)}
            self.counters.resets += len(resets)
            self.counters.reset_calls += 1
        acts = [r for r in requests if r.kind == "act"]
        outcomes: dict[int, StepOutcome] = {}
        if acts:
            actions: list[Any] = [None] * self.n_slots
            for r in acts:
                actions[r.slot] = r.action
            stepped = tb.step(actions)
            for r in acts:
                out = stepped[r.slot]
                assert out is not None
                outcomes[r.slot] = out
            self.counters.actions += len(acts)
            self.counters.step_calls += 1
        qpos, p = tb.observe()
        variants = tb.batch.variant()
        replies = []
        for r in requests:
            snapshot = SlotSnapshot(
                proprio=proprio_fields(p, r.slot, tb.batch.arms),
                qpos=np.array(qpos[r.slot]),
                slot=r.slot,
                variant=int(variants[r.slot]),
                gcs={arm: np.array(p.gc[r.slot, i]) for i, arm in enumerate(tb.batch.arms)},
                progress=int(tb.progress[r.slot]),
                objects=_object_poses(qpos[r.slot], tb.batch.objects),
            )
            replies.append(SimReply(snapshot, reports.get(r.slot), outcomes.get(r.slot)))
        return replies


def _object_poses(
    qpos: np.ndarray, objects: Sequence[tuple[str, int]]
) -> dict[str, dict[str, list[float]]]:
    """Each free object's pose read from one slot's qpos, rounded to 0.1 mm / 1e-4."""
    return {
        name: {
            "pos": [round(float(x), 4) for x in qpos[a : a + 3]],
            "quat": [round(float(x), 4) for x in qpos[a + 3 : a + 7]],
        }
        for name, a in objects
    }


class RenderService:
    """Batches the render requests of many episodes of one task into pool requests."""

    def __init__(
        self,
        pool: Renderer,
        task_name: str,
        settings: ImageSettings,
        *,
        window_s: float = 0.005,
        source: Any = None,
    ):
        self.pool = pool
        self.task_name = task_name
        self.settings = settings
        self.source = source  # the physics batch the pool reads states from (see Renderer)
        # a pool that serves requests side by side says how many (`concurrent_requests`)
        self._batcher: MicroBatcher[list[RenderItem], list[bytes]] = MicroBatcher(
            self._run,
            window_s=window_s,
            name=f"render-{task_name}",
            concurrency=max(1, int(getattr(pool, "concurrent_requests", 1))),
        )

    async def render(self, items: Sequence[RenderItem]) -> list[bytes]:
        return await self._batcher.submit(list(items))

    @property
    def stats(self):
        return self._batcher.stats

    def _run(self, requests: Sequence[list[RenderItem]]) -> list[list[bytes]]:
        flat = [item for req in requests for item in req]
        images = self.pool.render(self.task_name, flat, self.settings, source=self.source)
        out, i = [], 0
        for req in requests:
            out.append(images[i : i + len(req)])
            i += len(req)
        return out

    async def close(self) -> None:
        await self._batcher.close()
