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

Speed and memory: a sweep a hundred times larger holds 200,000 lines. Pydantic reads each
line straight from its JSON (`ResultLine`, ~7 us a line; decoding to a dict and validating
that took ~45 us); a line it refuses is read again the slow way, `json.loads` then
`parse_record`, only to say why in the words above. A validated model carries the set of the
fields its input named (2.3 KB for a ledger line's 32, 0.7 KB for its tokens'), the same set
for nearly every line: records share one (`_share_fields_set`), 1.5 KB a record instead of
4.5 KB.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import ConfigDict, Field, ValidationError

from vabench.agent.records import RECORD_VERSION, EpisodeResult
from vabench.run_layout import RunDir

Key = tuple[str, str, str, int, int]
"""(model, track, task, seed, run): one planned episode."""


class ReportError(ValueError):
    """Bad or missing input to the report; the message names the file (and line, field)."""


class ResultLine(EpisodeResult):
    """One results.jsonl line as read: the episode's `EpisodeResult` plus the ledger's envelope
    (`track`, `episode_dir`), which `model_dump` leaves out, so it dumps as the result it
    holds. Keys it does not know are ignored; `v` must be present (its value is checked)."""

    model_config = ConfigDict(extra="ignore")
    v: int
    track: str = Field(exclude=True)
    episode_dir: str = Field(default="", exclude=True)


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
    envelope = {"track": track, "episode_dir": str(obj.get("episode_dir", ""))}
    try:
        result = ResultLine.model_validate({**obj, **envelope})
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
    _share_fields_set(result)
    return Record(track=track, result=result, line=line, episode_dir=result.episode_dir)


_FIELDS_SETS: dict[tuple[type, frozenset[str]], set[str]] = {}


def _share_fields_set(result: ResultLine) -> None:
    """Give the result (and its tokens) the one set object of the fields it was given, shared
    with every record given the same fields (see the module docstring). The records are read,
    never assigned to (an assignment adds the field to the set: harmless when it is in it
    already, as for a ledger line, which names every field)."""
    for model in (result, result.tokens):
        fields = model.__pydantic_fields_set__
        shared = _FIELDS_SETS.setdefault((type(model), frozenset(fields)), fields)
        object.__setattr__(model, "__pydantic_fields_set__", shared)


def read_line(raw: bytes, where: str, line: int) -> Record:
    """One line as `parse_record` reads it, the fast way when pydantic takes the JSON as it is
    (see the module docstring); raises `json.JSONDecodeError` for a line that is not JSON and
    `UnicodeDecodeError` for one that is not UTF-8."""
    try:
        result = ResultLine.model_validate_json(raw)
    except ValidationError:
        result = None
    if (
        result is not None
        and result.v == RECORD_VERSION
        and result.track
        and result.success == (result.status == "success")
        and 0 <= result.progress <= result.n_checkpoints
    ):
        _share_fields_set(result)
        return Record(result.track, result, line, result.episode_dir)
    return parse_record(json.loads(raw.decode("utf-8")), where, line)


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
    lines = path.read_bytes().split(b"\n")
    # text ending in "\n" leaves a final "" that is not a line; a final non-empty piece is a
    # line written without its newline, the only place a crash can cut a record short.
    last_unterminated = len(lines) - 1 if lines[-1] != b"" else -1
    out = Results(path=path)
    first_scored: dict[Key, int] = {}
    for i, raw in enumerate(lines):
        if not raw.strip():
            continue
        where = f"{path}:{i + 1}"
        try:
            record = read_line(raw, where, i + 1)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            if i == last_unterminated:  # a write cut short, perhaps inside a character
                out.truncated_tail = True
                continue
            why = exc.msg if isinstance(exc, json.JSONDecodeError) else "not UTF-8"
            raise ReportError(f"{where}: not valid JSON ({why})") from None
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
