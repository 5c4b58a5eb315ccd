"""The learning stage of a sweep: one demonstration summary per (model, family), learned once.

Before a model's first episode of a family on a track that reads summaries, the model whose
summary the track reads (`TrackSpec.summary_source`: the episode's own model for `own`, the
named one for `shared:<model>`) studies the family's demonstration in a learning session
(`vabench.agent.learning`) and the outcome is stored:

    RUN_DIR/summaries/<model>/<family>.json      the LearningResult (summary and its text)
    RUN_DIR/summaries/<model>/<family>/          the session's events.jsonl

Every later episode of that (model, family), on every seed, run and track, reads the stored
summary: a family is learned once per sweep directory, also across processes (a file lock per
(model, family): Ray cells of one model wait for the one learning it) and across resumed runs.

Which family and which videos (FACTS, "Demonstration protocol"): a task reads the summary of
`Task.summary_family` (held-out variants: their base family, without a video of their own),
learned from the videos of `Task.demo_families` (the basket: the four atomic videos shown as
one frame index). Videos come from `vabench.demos` (cached under `learning.demo_cache`,
built when missing).

Outcomes: `learned` - the summary text goes into every observation of those episodes;
`failed` (the model did not produce an accepted summary within the session's budgets) and
`error` (the provider rejected one learning request) - stored and final: the episodes run
without a summary and record `summary_status="failed"`; a refusal of the endpoint itself (a
wrong key, an unknown model: `RequestRejected.fatal`) is not stored: it stops the sweep and the
next invocation learns again; `infrastructure_error` (the provider failed
beyond the pool's retries) - not stored: the episodes needing it end as infrastructure errors,
are re-run in the next retry round, and the session is tried again then.
"""

from __future__ import annotations

import asyncio
import fcntl
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vabench.agent.demonstration import DemoFrames
from vabench.agent.learning import (
    LearningLimits,
    LearningResult,
    learn_summary,
    read_result,
    write_result,
)
from vabench.agent.records import EpisodeRecorder, SummaryStatus
from vabench.llm_pool.errors import RequestRejected
from vabench.llm_pool.pool import LLMPool
from vabench.run_layout import RunDir
from vabench.tasks import get_task
from vabench.tasks.base import Task

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SummaryUse:
    """What one episode's observations carry, and how to record it."""

    mode: str
    """own | none | shared:<model>"""
    source: str | None
    """The model whose summary is shown; None when none is."""
    status: SummaryStatus
    text: str | None = None
    unavailable: str | None = None
    """Set when the summary could not be had for an infrastructure reason (the episode is not
    run: it ends as an infrastructure error and is retried)."""


def load_demo_frames(task: Task, cache_dir: Path) -> DemoFrames:
    """The demonstration a session on `task`'s summary family studies (blocking: may simulate
    and render a missing video)."""
    from vabench.demos import build_demo, load_demo  # the simulator and renderer: lazily

    parts = []
    for family in task.demo_families:
        build_demo(family, cache_dir, mp4=False)  # no ffmpeg subprocess forked from a sweep
        demo = load_demo(family, cache_dir)
        parts.append((get_task(family).instruction, DemoFrames(demo.frames, demo.info.fps, family)))
    if len(parts) == 1:
        return parts[0][1]
    return DemoFrames.concat(parts, label="+".join(task.demo_families))


class SummaryStage:
    """Learns and serves the summaries of one sweep directory (see the module docstring)."""

    def __init__(
        self,
        run_dir: Path,
        llm: LLMPool,
        *,
        demo_cache: Path,
        limits: LearningLimits | None = None,
    ):
        self.run_dir = run_dir
        self.llm = llm
        self.demo_cache = demo_cache
        self.limits = limits or LearningLimits()
        self.sessions = 0
        """Learning sessions run by this stage (not counting stored ones it reused)."""
        self._results: dict[tuple[str, str], LearningResult] = {}
        self._locks: dict[tuple[str, str], asyncio.Lock] = {}
        self._refused: dict[str, RequestRejected] = {}
        """Models whose endpoint refused a learning request (`RequestRejected.fatal`): every
        later caller gets the same error at once instead of one more refused call each."""

    async def for_episode(self, mode: str, source: str | None, task_name: str) -> SummaryUse:
        """The summary an episode of `task_name` shows on a track of summary `mode` whose
        summaries come from model `source` (None: the track reads none)."""
        if source is None:
            return SummaryUse(mode, None, "none")
        result = await self.result(source, get_task(task_name))
        if result.status == "infrastructure_error":
            why = f"learning stage of {source}/{result.task}: {result.error}"
            return SummaryUse(mode, source, "failed", unavailable=why)
        if result.summary_text is None:
            return SummaryUse(mode, None, "failed")
        return SummaryUse(mode, source, "learned", result.summary_text)

    async def result(self, model: str, task: Task) -> LearningResult:
        """The learning result of (model, task's summary family), learning it first if none is
        known. An infrastructure failure is served to every episode of this retry round (one
        session per round, not one per waiting episode) and never stored on disk;
        `forget_failures` lets the next round try again."""
        key = (model, task.summary_family)
        if key in self._results:
            return self._results[key]
        lock = self._locks.setdefault(key, asyncio.Lock())
        async with lock:
            if model in self._refused:
                raise self._refused[model]
            if key not in self._results:
                try:
                    self._results[key] = await self._learn_once(model, get_task(key[1]))
                except RequestRejected as err:  # fatal ones only reach here
                    self._refused[model] = err
                    raise
            return self._results[key]

    def forget_failures(self) -> None:
        """Start a retry round: sessions that failed for infrastructure reasons are tried again
        when next needed."""
        self._results = {
            k: r for k, r in self._results.items() if r.status != "infrastructure_error"
        }

    async def _learn_once(self, model: str, task: Task) -> LearningResult:
        files = RunDir(self.run_dir)
        path = files.summary(model, task.name)
        lock = files.summary_lock(model, task.name)
        # Another process (a Ray cell of the same model) may be learning this family: the file
        # lock makes it learn once; waiting for it must not block the event loop.
        fd = await asyncio.to_thread(_acquire, lock)
        try:
            if path.exists():
                stored = read_result(path)
                log.info(
                    "summary %s/%s: reusing the stored one (%s)", model, task.name, stored.status
                )
                return stored
            demo = await asyncio.to_thread(load_demo_frames, task, self.demo_cache)
            log.info(
                "summary %s/%s: learning from %d frames of %s",
                model,
                task.name,
                len(demo),
                ", ".join(task.demo_families),
            )
            recorder = EpisodeRecorder(files.learning_session(model, task.name).path)
            try:
                result = await learn_summary(
                    task, demo, self.llm, model, recorder=recorder, limits=self.limits
                )
            finally:
                recorder.close()
            self.sessions += 1
            if result.status != "infrastructure_error":
                write_result(path, result)
            log.info(
                "summary %s/%s: %s after %d calls (%s)",
                model,
                task.name,
                result.status,
                result.model_calls,
                result.stop_reason,
            )
            return result
        finally:
            _release(fd)


def _acquire(path: Path) -> Any:
    path.parent.mkdir(parents=True, exist_ok=True)
    f = open(path, "w")  # noqa: SIM115 - held across awaits, closed by _release
    fcntl.flock(f, fcntl.LOCK_EX)
    return f


def _release(f: Any) -> None:
    fcntl.flock(f, fcntl.LOCK_UN)
    f.close()
