"""Annotations on disk: one append-only JSONL file per annotator under RUN_DIR/annotations/.

A line is one judgment:

    {"v": 1, "annotator": "alice", "episode": "local/active/grasp_single_cube/seed_1000/run_1",
     "item": "gate_error" | "TL" | ..., "value": 0 | 1 | null, "time": 1795595021.81,
     "rubric": "va-bench-rubric-1", "source": "human" | "judge:<model>" | "import", "note": ...}

`value: null` withdraws an earlier judgment. Nothing is rewritten: a later judgment of the same
(annotator, episode, item) supersedes an earlier one, "later" meaning a larger `time`, then a
later line (imported CSV rows keep their original times). Each line goes to disk as one
`write()` on an O_APPEND descriptor under an exclusive fcntl lock, so two browsers, two viewer
processes or a judge writing at once never interleave or lose a line.

Reading never stops at a bad line: a malformed line is reported (`file:line: field: problem`)
and skipped, so the statistics still run.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vabench.diagnostics.criteria import GATES, ITEMS, RUBRIC_VERSION, gate_of
from vabench.diagnostics.episodes import RunIndex, UnknownEpisode
from vabench.run_layout import RunDir, annotation_name

JUDGMENT_VERSION = 1
ANNOTATOR_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
"""Plain names only: they become file names and appear in HTML."""


class AnnotationError(ValueError):
    """A judgment that cannot be recorded; `field` names what is wrong."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


@dataclass(frozen=True)
class Judgment:
    annotator: str
    episode: str
    item: str
    value: int | None
    time: float
    rubric: str = RUBRIC_VERSION
    source: str = "human"
    note: str | None = None
    line: int = 0
    """Position in its file (1-based), the tie-breaker of equal times."""

    def record(self) -> dict[str, Any]:
        out = {
            "v": JUDGMENT_VERSION,
            "annotator": self.annotator,
            "episode": self.episode,
            "item": self.item,
            "value": self.value,
            "time": self.time,
            "rubric": self.rubric,
            "source": self.source,
        }
        if self.note:
            out["note"] = self.note
        return out


def check_annotator(name: Any) -> str:
    if not isinstance(name, str) or not ANNOTATOR_PATTERN.fullmatch(name):
        raise AnnotationError(
            "annotator",
            f"{name!r} is not a plain name (1-64 letters, digits, '.', '_', '-', starting with "
            "a letter or digit)",
        )
    return name


def check_item(item: Any) -> str:
    if item not in ITEMS:
        raise AnnotationError("item", f"unknown criterion or gate {item!r}; valid: {list(ITEMS)}")
    return item


def check_value(value: Any) -> int | None:
    if value is None or (value in (0, 1) and not isinstance(value, float)):
        return None if value is None else int(value)
    raise AnnotationError("value", f"expected 0, 1 or null, got {value!r}")


def parse_judgment(obj: Any, line: int = 0) -> Judgment:
    """Validate one decoded line (or CSV row); raises AnnotationError naming the field."""
    if not isinstance(obj, Mapping):
        raise AnnotationError("line", f"expected a JSON object, got {type(obj).__name__}")
    if obj.get("v", JUDGMENT_VERSION) != JUDGMENT_VERSION:
        raise AnnotationError("v", f"judgment version {obj.get('v')!r}, expected 1")
    annotator = check_annotator(obj.get("annotator"))
    episode = obj.get("episode")
    if not isinstance(episode, str) or not episode:
        raise AnnotationError("episode", f"expected an episode id, got {episode!r}")
    item = check_item(obj.get("item"))
    if "value" not in obj:
        raise AnnotationError("value", "missing")
    value = check_value(obj["value"])
    t = obj.get("time")
    if isinstance(t, bool) or not isinstance(t, int | float):
        raise AnnotationError("time", f"expected seconds since the epoch, got {t!r}")
    note = obj.get("note")
    if note is not None and not isinstance(note, str):
        raise AnnotationError("note", f"expected text, got {type(note).__name__}")
    return Judgment(
        annotator,
        episode,
        item,
        value,
        float(t),
        str(obj.get("rubric", RUBRIC_VERSION)),
        str(obj.get("source", "human")),
        note,
        line,
    )


Key = tuple[str, str, str]
"""(episode, annotator, item)."""


def current(judgments: Iterable[Judgment]) -> dict[Key, Judgment]:
    """The judgment in force for every (episode, annotator, item): the latest, withdrawals
    removed."""
    latest: dict[Key, Judgment] = {}
    for j in judgments:
        key = (j.episode, j.annotator, j.item)
        held = latest.get(key)
        if held is None or (j.time, j.line) >= (held.time, held.line):
            latest[key] = j
    return {k: j for k, j in latest.items() if j.value is not None}


def majority(values: Iterable[int]) -> int | None:
    """1 when more than half are 1 (the paper's >= 2 of 3); None without votes."""
    votes = list(values)
    return None if not votes else int(2 * sum(votes) > len(votes))


def gate_votes(state: Mapping[Key, Judgment], episode: str, gate: str) -> dict[str, int]:
    """Every annotator's vote on one gate of one episode (a scan of `state`: for many look-ups,
    build `GateVotes` once)."""
    return {
        a: j.value
        for (e, a, i), j in state.items()
        if e == episode and i == gate and j.value is not None
    }


class GateVotes:
    """The gate votes of a state, indexed by (episode, gate): one pass over the state, then a
    look-up per judgment, so checking n judgments against a store of m costs n + m, not n x m."""

    def __init__(self, state: Mapping[Key, Judgment]):
        self._votes: dict[tuple[str, str], dict[str, int]] = {}
        for (episode, annotator, item), j in state.items():
            if item in GATES and j.value is not None:
                self._votes.setdefault((episode, item), {})[annotator] = j.value

    def of(self, episode: str, gate: str) -> dict[str, int]:
        return self._votes.get((episode, gate), {})


def activation(state: Mapping[Key, Judgment], episode: str, annotator: str, item: str) -> str:
    """'' when `annotator` may judge `item` on `episode`, else why not. A gated criterion is
    activated by the annotator's own gate vote of 1 (stage one) or by a majority gate of 1
    among all annotators (stage two: everyone then judges it)."""
    gate = gate_of(item)
    if gate is None:
        return ""
    return inactive_reason(item, episode, annotator, gate_votes(state, episode, gate))


def inactive_reason(
    item: str, episode: str, annotator: str, votes: Mapping[str, int], remedy: str = ""
) -> str:
    """'' when `votes` (annotator -> vote on `item`'s gate) activate `item` for `annotator`,
    else a sentence saying what is missing; `remedy` replaces its last clause (what to do)."""
    gate = gate_of(item)
    if gate is None or votes.get(annotator) == 1 or majority(votes.values()) == 1:
        return ""
    ones = sum(votes.values())
    if not votes:
        state = f"nobody has voted its gate {gate} ({GATES[gate].name}) yet"
    else:
        own = votes.get(annotator)
        mine = f"{annotator} has not voted it" if own is None else f"{annotator} voted 0"
        state = (
            f"its gate {gate} ({GATES[gate].name}) is not 1: {mine}, and {ones} of "
            f"{len(votes)} vote(s) are 1, no majority"
        )
    todo = remedy or (
        f"record {annotator}'s {gate} vote first (1 = yes to {GATES[gate].question!r})"
    )
    return f"criterion {item} is not activated for episode {episode!r}: {state}; {todo}"


@dataclass
class Loaded:
    judgments: list[Judgment] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    """One message per skipped line: `file:line: field: problem`."""


class AnnotationStore:
    """The annotations of one run directory: validated appends, tolerant reads."""

    def __init__(self, index: RunIndex):
        self.index = index
        self._run = RunDir(index.run_dir)
        self.directory = self._run.annotations
        self._cache: dict[Path, tuple[tuple[int, int], Loaded]] = {}

    def path(self, annotator: str) -> Path:
        return self._run.annotation_file(check_annotator(annotator))

    # -- reading ------------------------------------------------------------------------------
    def load(self) -> Loaded:
        out = Loaded()
        if not self.directory.is_dir():
            return out
        for path in self._run.annotation_files():
            part = self._load_file(path)
            out.judgments += part.judgments
            out.problems += part.problems
        return out

    def _load_file(self, path: Path) -> Loaded:
        stat = path.stat()
        stamp = (stat.st_size, stat.st_mtime_ns)
        cached = self._cache.get(path)
        if cached is not None and cached[0] == stamp:
            return cached[1]
        out = Loaded()
        data = path.read_bytes()
        lines = data.split(b"\n")
        for n, raw in enumerate(lines, 1):
            if not raw.strip():
                continue
            where = f"{path}:{n}"
            if n == len(lines) and not data.endswith(b"\n"):
                out.problems.append(f"{where}: a truncated last line (a write cut short) skipped")
                continue
            try:
                j = parse_judgment(json.loads(raw), n)
            except json.JSONDecodeError as err:
                out.problems.append(f"{where}: not valid JSON ({err.msg}); line skipped")
                continue
            except AnnotationError as err:
                out.problems.append(f"{where}: {err}; line skipped")
                continue
            if annotation_name(j.annotator) != path.name:
                out.problems.append(
                    f"{where}: annotator: {j.annotator!r} in the file of {path.stem!r}; skipped"
                )
            elif j.episode not in self.index.episodes:
                unknown = UnknownEpisode(j.episode, self.index.run_dir)
                out.problems.append(f"{where}: episode: {unknown}; skipped")
            else:
                out.judgments.append(j)
        self._cache[path] = (stamp, out)
        return out

    def state(self) -> dict[Key, Judgment]:
        return current(self.load().judgments)

    # -- writing ------------------------------------------------------------------------------
    def check(
        self, annotator: Any, episode: Any, item: Any, value: Any, state: Mapping[Key, Judgment]
    ) -> Judgment:
        """A judgment `record` would accept (AnnotationError naming the field otherwise)."""
        annotator = check_annotator(annotator)
        episode = self.check_episode(episode)
        item = check_item(item)
        value = check_value(value)
        if value is not None and (why := activation(state, episode, annotator, item)):
            raise AnnotationError("item", why)
        return Judgment(annotator, episode, item, value, time.time())

    def check_episode(self, episode: Any) -> str:
        """`episode` if it is a scored episode of the run (AnnotationError otherwise)."""
        if not isinstance(episode, str) or episode not in self.index.episodes:
            raise AnnotationError("episode", str(UnknownEpisode(str(episode), self.index.run_dir)))
        ref = self.index.episodes[episode]
        if not ref.result.scored:
            raise AnnotationError(
                "episode",
                f"{episode!r} was never scored (status {ref.result.status}); "
                "only scored episodes are annotated",
            )
        return episode

    def record(
        self,
        annotator: Any,
        episode: Any,
        item: Any,
        value: Any,
        *,
        source: str = "human",
        note: str | None = None,
    ) -> Judgment:
        """Validate one judgment against the current state and append it."""
        j = self.check(annotator, episode, item, value, self.state())
        j = Judgment(j.annotator, j.episode, j.item, j.value, j.time, source=source, note=note)
        self.append([j])
        return j

    def append(self, judgments: Iterable[Judgment]) -> None:
        """Append already-validated judgments, one locked write per annotator file."""
        by_annotator: dict[str, list[str]] = {}
        for j in judgments:
            by_annotator.setdefault(j.annotator, []).append(json.dumps(j.record()) + "\n")
        self.directory.mkdir(parents=True, exist_ok=True)
        for annotator, lines in by_annotator.items():
            data = "".join(lines).encode("utf-8")
            with _locked_append(self.path(annotator)) as fd:
                while data:  # one write() in practice; a short one is finished under the lock
                    data = data[os.write(fd, data) :]


@contextlib.contextmanager
def _locked_append(path: Path) -> Iterator[int]:
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX)
        yield fd
    finally:
        os.close(fd)  # releases the lock
