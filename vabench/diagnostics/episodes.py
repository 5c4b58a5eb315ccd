"""The episodes of a run directory, as the viewer and the diagnostics see them (read-only).

An episode id is its directory under RUN_DIR/episodes/, `<model>/<track>/<task>/seed_<s>/run_<r>`
(the ledger's `episode_dir` without the leading `episodes/`). Ids are only ever looked up in
this index, never joined to a path as given, so a request cannot name a file outside the run.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vabench.agent.records import read_events
from vabench.run_layout import EpisodeDir, RunDir, episode_id, episode_rel
from vabench.run_records import Record, ReportError, load_results


class RunDirError(ValueError):
    """A run directory that cannot be read; the message names the path."""


class UnknownEpisode(KeyError):
    def __init__(self, episode: str, run_dir: Path):
        super().__init__(episode)
        self.message = f"unknown episode {episode!r}: not in {RunDir(run_dir).results}"

    def __str__(self) -> str:
        return self.message


@dataclass(frozen=True)
class EpisodeRef:
    id: str
    track: str
    record: Record

    @property
    def result(self):
        return self.record.result

    def summary(self) -> dict[str, Any]:
        """The run page's row: identity, outcome, checkpoints, counts."""
        r = self.result
        return {
            "id": self.id,
            "model": r.model,
            "track": self.track,
            "task": r.task,
            "seed": r.seed,
            "run": r.run,
            "protocol": r.protocol,
            "status": r.status,
            "success": r.success,
            "scored": r.scored,
            "stop_reason": r.stop_reason,
            "steps_used": r.steps_used,
            "step_budget": r.step_budget,
            "robot_actions": r.robot_actions,
            "camera_actions": r.camera_actions,
            "invalid_actions": r.invalid_actions,
            "invalid_outputs": r.invalid_outputs,
            "checkpoints_reached": list(r.checkpoints_reached),
            "progress": r.progress,
            "n_checkpoints": r.n_checkpoints,
        }


@dataclass
class RunIndex:
    run_dir: Path
    episodes: dict[str, EpisodeRef]

    @classmethod
    def load(cls, run_dir: Path | str) -> RunIndex:
        run_dir = Path(run_dir)
        if not run_dir.is_dir():
            raise RunDirError(f"{run_dir}: no such directory (give a sweep's run directory)")
        try:
            results = load_results(run_dir)
        except ReportError as err:
            raise RunDirError(str(err)) from None
        episodes: dict[str, EpisodeRef] = {}
        for record in results.scored + results.unscored:
            r = record.result
            rel = record.episode_dir or episode_rel(r.model, record.track, r.task, r.seed, r.run)
            ref = EpisodeRef(episode_id(rel), record.track, record)
            episodes[ref.id] = ref
        ordered = dict(sorted(episodes.items(), key=lambda kv: _order(kv[1])))
        return cls(run_dir.resolve(), ordered)

    def get(self, episode: str) -> EpisodeRef:
        try:
            return self.episodes[episode]
        except KeyError:
            raise UnknownEpisode(episode, self.run_dir) from None

    def directory(self, episode: str) -> Path:
        return RunDir(self.run_dir).episodes / self.get(episode).id

    def events(self, episode: str) -> list[dict[str, Any]]:
        path = self.directory(episode)
        if not EpisodeDir(path).events.is_file():
            return []
        return read_events(path)

    @property
    def scored(self) -> list[EpisodeRef]:
        return [e for e in self.episodes.values() if e.result.scored]


def _order(e: EpisodeRef) -> tuple[Any, ...]:
    r = e.result
    return (r.model, e.track, r.task, r.seed, r.run)


def task_instruction(task: str) -> str:
    """The instruction the model read (imports the task registry, which loads JAX: lazily)."""
    from vabench.tasks import REGISTRY

    spec = REGISTRY.get(task)
    return spec.instruction if spec is not None else ""
