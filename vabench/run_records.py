"""Reading a sweep's results.jsonl into validated records.

Each line is `{"v": 1, "track": ..., "episode_dir": ..., **EpisodeResult fields}` (written by
the sweep, one line per finished episode). Rules:

- A final line that has no newline and does not parse is a write cut short by a crash: it is
  dropped and reported (`Results.truncated_tail`), never an error. Any other line that does
  not parse, is not an object, or fails validation is an error naming `file:line` and the field.
- Blank lines are skipped.
- Keys this reader does not know are ignored, so the sweep may add fields without breaking it.
- Only scored records (status success/failure) feed the statistics. At most one scored record
  may exist per (model, track, task, seed, run); a second is an error naming both lines.
  Unscored records (infrastructure_error, error) are kept for counting only.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from vabench.agent.records import RECORD_VERSION, EpisodeResult
from vabench.run_layout import RunDir

Key = tuple[str, str, str, int, int]
"""(model, track, task, seed, run): one planned episode."""


class ReportError(ValueError):
    """Bad or missing input to the report; the message names the file (and line, field)."""


@dataclass(frozen=True)
class Record:
    """One results.jsonl line: the episode's result plus the track it ran under."""

    track: str
    result: EpisodeResult
    line: int
    episode_dir: str = ""

    @property
    def key(self) -> Key:
        r = self.result
        return (r.model, self.track, r.task, r.seed, r.run)


@dataclass
class Results:
    path: Path
    scored: list[Record] = field(default_factory=list)
    unscored: list[Record] = field(default_factory=list)
    truncated_tail: bool = False
    """True when a crash-truncated final line was dropped."""
    retried: dict[tuple[str, str], int] = field(default_factory=dict)
    """(model, track) -> infrastructure failures that were run again (from the sweep's
    infrastructure log, `run_layout.INFRASTRUCTURE`: one line per attempt)."""


_ENVELOPE = ("track", "episode_dir")


def parse_record(obj: Any, where: str, line: int) -> Record:
    """Validate one decoded line; `where` is "file:line" for error messages."""
    if not isinstance(obj, dict):
        raise ReportError(f"{where}: expected a JSON object, got {type(obj).__name__}")
    version = obj.get("v")
    if version != RECORD_VERSION:
        raise ReportError(
            f"{where}: field 'v': record version {version!r}, this reader knows {RECORD_VERSION}"
        )
    track = obj.get("track")
    if not isinstance(track, str) or not track:
        raise ReportError(f"{where}: field 'track': expected a non-empty string, got {track!r}")
    episode_dir = obj.get("episode_dir", "")
    known = {k: v for k, v in obj.items() if k in EpisodeResult.model_fields}
    try:
        result = EpisodeResult.model_validate(known)
    except ValidationError as exc:
        raise ReportError(f"{where}: {validation_problems(exc)}") from None
    if result.success != (result.status == "success"):
        raise ReportError(
            f"{where}: field 'success': {result.success} contradicts status {result.status!r}"
        )
    if not 0 <= result.progress <= result.n_checkpoints:
        raise ReportError(
            f"{where}: field 'progress': {result.progress} outside "
            f"[0, n_checkpoints={result.n_checkpoints}]"
        )
    return Record(track=track, result=result, line=line, episode_dir=str(episode_dir))


def validation_problems(exc: ValidationError) -> str:
    """Pydantic's errors as one line: "field 'a.b': problem; field 'c': problem"."""
    return "; ".join(
        f"field '{'.'.join(str(p) for p in e['loc'])}': {e['msg']}" for e in exc.errors()
    )


def load_results(run_dir: Path | str) -> Results:
    """Read and validate RUN_DIR/results.jsonl (see the module docstring for the rules)."""
    files = RunDir(Path(run_dir))
    path = files.results
    if not path.is_file():
        raise ReportError(f"{path}: not found (is {run_dir} a sweep run directory?)")
    text = path.read_text(encoding="utf-8")
    lines = text.split("\n")
    # text ending in "\n" leaves a final "" that is not a line; a final non-empty piece is a
    # line written without its newline, the only place a crash can cut a record short.
    last_unterminated = len(lines) - 1 if lines[-1] != "" else -1
    out = Results(path=path)
    first_scored: dict[Key, int] = {}
    for i, raw in enumerate(lines):
        if not raw.strip():
            continue
        where = f"{path}:{i + 1}"
        try:
            obj = json.loads(raw)
        except json.JSONDecodeError as exc:
            if i == last_unterminated:
                out.truncated_tail = True
                continue
            raise ReportError(f"{where}: not valid JSON ({exc.msg})") from None
        record = parse_record(obj, where, i + 1)
        if not record.result.scored:
            out.unscored.append(record)
            continue
        if record.key in first_scored:
            model, track, task, seed, run = record.key
            raise ReportError(
                f"{where}: duplicate scored record for model={model!r} track={track!r} "
                f"task={task!r} seed={seed} run={run}; the first is at line "
                f"{first_scored[record.key]} (running the sweep command again collapses it)"
            )
        first_scored[record.key] = i + 1
        out.scored.append(record)
    out.retried = count_retried(files.infrastructure)
    if not out.scored and not out.unscored:
        raise ReportError(f"{path}: no records (empty file)")
    if not out.scored:
        statuses = sorted({r.result.status for r in out.unscored})
        raise ReportError(
            f"{path}: no scored episode (status success/failure); {len(out.unscored)} "
            f"unscored ({', '.join(statuses)})"
        )
    return out


def count_retried(path: Path) -> dict[tuple[str, str], int]:
    """(model, track) -> lines of the sweep's infrastructure log; {} when it does not exist.

    Only counted, never scored; a line without a model and track (a crash-truncated tail) is
    skipped rather than failing the report over a file that does not feed any statistic.
    """
    counts: dict[tuple[str, str], int] = {}
    for obj in jsonl_objects(path):
        if "model" in obj and "track" in obj:
            key = (str(obj["model"]), str(obj["track"]))
            counts[key] = counts.get(key, 0) + 1
    return dict(sorted(counts.items()))


def jsonl_objects(path: Path) -> Iterator[dict[str, Any]]:
    """The JSON objects of a JSONL file that is counted or billed, never scored: a line that
    does not parse (cut by a crash) or is not an object is skipped; nothing when the file does
    not exist."""
    if not path.is_file():
        return
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            obj = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(obj, dict):
            yield obj
