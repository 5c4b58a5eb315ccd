"""The learning stage of a sweep: one demonstration summary per (model, family), learned once.

Before a model's first episode of a family on a track that reads summaries, the model whose
summary the track reads (`TrackSpec.summary_source`: the episode's own model for `own`, the
named one for `shared:<model>`) studies the family's demonstration in a learning session
(`vabench.agent.learning`) and the outcome is stored:

    RUN_DIR/summaries/<model>/<family>.json      the LearningResult (summary and its text) of
                                                 the last attempt, the earlier ones inside
    RUN_DIR/summaries/<model>/<family>/          the last attempt's events.jsonl, learning.json
    RUN_DIR/summaries/<model>/<family>/attempt_<n>/   an earlier attempt's, set aside

Every later episode of that (model, family), on every seed, run and track, reads the stored
summary: a family is learned once per sweep directory, also across processes (a file lock per
(model, family): Ray cells of one model wait for the one learning it) and across resumed runs.

Which family and which videos (FACTS, "Demonstration protocol"): a task reads the summary of
`Task.summary_family` (held-out variants: their base family, without a video of their own),
learned from the videos of `Task.demo_families` (the basket: the four atomic videos shown as
one frame index, with no scene). Videos come from `vabench.demos` (cached under
`learning.demo_cache`, built when missing); a single video comes with the scene it starts
from (`DemoScene`: the first observation an evaluation episode at the demo seed shows, text
and head-camera image, built from the demo's model-visible robot state and frame 0).

Attempts (the reference's learning script retries a failed run twice): a session that ends
`failed` is set aside (`attempt_<n>/`) and run again, up to `LEARNING_ATTEMPTS` sessions in
all; the stored result is the last one's, holding the earlier ones (`earlier_attempts`,
`attempt`). A sweep stopped between attempts goes on from the attempts set aside, so no
attempt is lost or run twice; a stored result is never learned again.

Outcomes: `learned` - the summary text goes into every observation of those episodes;
`failed` (no accepted summary within the session's budgets, in every attempt) and `error`
(the provider rejected one learning request) - stored and final: the episodes run without a
summary and record `summary_status="failed"`; a refusal of the endpoint itself (a wrong key,
an unknown model: `RequestRejected.fatal`) is not stored: it stops the sweep and the next
invocation learns again; `infrastructure_error` (the provider failed beyond the pool's
retries) - not stored, and not an attempt: the episodes needing it end as infrastructure
errors, are re-run in the next retry round, and the session is tried again then.
"""

from __future__ import annotations

import asyncio
import fcntl
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from vabench.agent.demonstration import DemoFrames, DemoScene, scene_observation
from vabench.agent.learning import (
    LearningLimits,
    LearningResult,
    learn_summary,
    read_result,
    write_result,
)
from vabench.agent.records import EpisodeRecorder, EpisodeResult, SummaryStatus
from vabench.agent.spec import EpisodeSpec
from vabench.llm_pool.errors import RequestRejected
from vabench.llm_pool.pool import LLMPool
from vabench.run_layout import ATTEMPT_PREFIX, EpisodeDir, RunDir
from vabench.tasks import get_task
from vabench.tasks.base import Task

log = logging.getLogger(__name__)

LEARNING_ATTEMPTS = 3
"""Learning sessions per (model, family) while they end `failed` (PROTOCOL_FACTS 6.5)."""


class SummaryRecordError(ValueError):
    """A stored learning result that cannot be read (unknown version, damaged file)."""


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
        parts.append((get_task(family), demo))
    if len(parts) == 1:
        ((family_task, demo),) = parts
        text = scene_observation(family_task.instruction, family_task.arms, demo.robot)
        scene = DemoScene(text, demo.frames[0])
        return DemoFrames(demo.frames, demo.info.fps, family_task.name, scene=scene)
    videos = [(t.instruction, DemoFrames(d.frames, d.info.fps, t.name)) for t, d in parts]
    return DemoFrames.concat(videos, label="+".join(task.demo_families))


class SummaryStage:
    """Learns and serves the summaries of one sweep directory (see the module docstring)."""

    def __init__(
        self,
        run_dir: Path,
        llm: LLMPool,
        *,
        demo_cache: Path,
        limits: LearningLimits | None = None,
        attempts: int = LEARNING_ATTEMPTS,
    ):
        if attempts < 1:
            raise ValueError(f"attempts must be >= 1, got {attempts}")
        self.run_dir = run_dir
        self.llm = llm
        self.demo_cache = demo_cache
        self.limits = limits or LearningLimits()
        self.attempts = attempts
        self.sessions = 0
        """Learning sessions run by this stage (each attempt counts; stored ones reused do
        not)."""
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
                stored = _read(path)
                log.info(
                    "summary %s/%s: reusing the stored one (%s)", model, task.name, stored.status
                )
                return stored
            session = files.learning_session(model, task.name)
            earlier = _set_aside_attempts(session)
            result = _left_over(session)  # a sweep stopped before storing its last attempt
            if result is not None and self._again(result, earlier):
                _set_aside(session)
                earlier.append(result)
                result = None
            if result is None:
                demo = await asyncio.to_thread(load_demo_frames, task, self.demo_cache)
                while True:
                    result = await self._attempt(model, task, demo, session, len(earlier) + 1)
                    if not self._again(result, earlier):
                        break
                    _set_aside(session)
                    earlier.append(result)
            result = result.model_copy(
                update={"attempt": len(earlier) + 1, "earlier_attempts": earlier}
            )
            if result.status != "infrastructure_error":
                write_result(path, result)
            return result
        finally:
            _release(fd)

    def _again(self, result: LearningResult, earlier: list[LearningResult]) -> bool:
        """Whether a session that ended as `result` after `earlier` attempts is run again."""
        return result.status == "failed" and len(earlier) + 1 < self.attempts

    async def _attempt(
        self, model: str, task: Task, demo: DemoFrames, session: EpisodeDir, attempt: int
    ) -> LearningResult:
        log.info(
            "summary %s/%s: learning from %d frames of %s (attempt %d of %d)",
            model,
            task.name,
            len(demo),
            ", ".join(task.demo_families),
            attempt,
            self.attempts,
        )
        recorder = EpisodeRecorder(session.path)
        try:
            result = await learn_summary(
                task, demo, self.llm, model, recorder=recorder, limits=self.limits, attempt=attempt
            )
        finally:
            recorder.close()
        self.sessions += 1
        log.info(
            "summary %s/%s: %s after %d calls (%s)",
            model,
            task.name,
            result.status,
            result.model_calls,
            result.stop_reason,
        )
        return result


def _read(path: Path) -> LearningResult:
    try:
        return read_result(path)
    except (OSError, json.JSONDecodeError, ValidationError) as err:
        why = err.errors()[0]["msg"] if isinstance(err, ValidationError) else str(err)
        raise SummaryRecordError(f"{path}: not a learning result vabench reads: {why}") from None


def _set_aside_attempts(session: EpisodeDir) -> list[LearningResult]:
    """The attempts of this (model, family) set aside (`attempt_<n>/` holding a learning.json),
    in order."""
    if not session.path.is_dir():
        return []
    found = []
    for d in sorted(session.path.glob(f"{ATTEMPT_PREFIX}*"), key=_attempt_number):
        if EpisodeDir(d).learning_result.exists():
            found.append(_read(EpisodeDir(d).learning_result))
    return [r.model_copy(update={"attempt": i}) for i, r in enumerate(found, start=1)]


def _left_over(session: EpisodeDir) -> LearningResult | None:
    """The result of a session that ended but was neither stored nor set aside (the sweep
    stopped in between); None when there is none, or it ended with an infrastructure error (no
    attempt: the recorder sets its events aside as an interrupted log when the next starts)."""
    if not session.learning_result.exists():
        return None
    result = _read(session.learning_result)
    return None if result.status == "infrastructure_error" else result


def _attempt_number(path: Path) -> int:
    tail = path.name.removeprefix(ATTEMPT_PREFIX)
    return int(tail) if tail.isdigit() else 0


def _set_aside(session: EpisodeDir) -> None:
    """Move a finished attempt's files into `attempt_<n>/`, its learning.json last (an attempt
    folder without one is no attempt: see `_set_aside_attempts`)."""
    aside = session.next_attempt()
    aside.mkdir()
    for name in (session.events, session.frames, session.learning_result):
        if name.exists():
            name.rename(aside / name.name)


def _acquire(path: Path) -> Any:
    path.parent.mkdir(parents=True, exist_ok=True)
    f = open(path, "w")  # noqa: SIM115 - held across awaits, closed by _release
    fcntl.flock(f, fcntl.LOCK_EX)
    return f


def _release(f: Any) -> None:
    fcntl.flock(f, fcntl.LOCK_UN)
    f.close()


def unavailable_result(spec: EpisodeSpec, budget: int, why: str) -> EpisodeResult:
    """The record of an episode not run because its summary could not be learned for an
    infrastructure reason (unscored; re-run in the next round)."""
    recorder = EpisodeRecorder(spec.out_dir)
    recorder.event("summary_unavailable", error=why)
    result = EpisodeResult(
        task=spec.task,
        seed=spec.seed,
        model=spec.model,
        protocol=spec.protocol,
        run=spec.run,
        status="infrastructure_error",
        success=False,
        stop_reason="infrastructure_error",
        error=why,
        step_budget=budget,
        n_checkpoints=len(get_task(spec.task).checkpoints),
        summary_mode=spec.summary_mode,
        summary_from=spec.summary_from,
        summary_status=spec.summary_status,
    )
    return recorder.finish(result)  # closes the recorder
