"""The run page's data at any size: an index kept current as the sweep appends, and the episode
list filtered and paged on the server.

A sweep a hundred times larger holds 200,000 episodes. Sending them all to the run page took
11 s to the first byte and a 100 MB body a browser then filters row by row, and reloading the
whole index after every ledger line took as long as starting the viewer (25 s). So:

- `LiveIndex` reads the ledger once (`RunIndex.load`), then only the lines appended since: a
  new line adds its episode in order. Anything else (the ledger cut, rewritten or replaced, a
  line that is not a new episode's record) loads it again from the start, as before.
- `Listing` answers the run page: one page of the episodes that pass the filters (model,
  track, task, outcome), how many pass, and every value each filter offers; and the
  neighbours of an episode in that order (the episode page's n/p keys).

The annotation store survives the index growing: the viewer refuses judgments of episodes it
does not know, so no judgment names an episode the index is about to gain.
"""

from __future__ import annotations

import heapq
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vabench.diagnostics.episodes import EpisodeRef, RunIndex
from vabench.run_layout import RunDir, episode_id, episode_rel
from vabench.run_records import ReportError, read_line

FILTERS = ("model", "track", "task", "outcome")
"""The run page's filters, by their query parameter."""
PAGE_SIZE = 500
MAX_PAGE = 5000


def outcome_of(ref: EpisodeRef) -> str:
    r = ref.result
    return ("success" if r.success else "failure") if r.scored else "unscored"


def _order(ref: EpisodeRef) -> tuple[Any, ...]:
    """The run page's order (the one `RunIndex.load` sorts by)."""
    r = ref.result
    return (r.model, ref.track, r.task, r.seed, r.run)


class LiveIndex:
    """`RunIndex` of a run whose ledger may still grow (see the module docstring)."""

    def __init__(self, run_dir: Path | str):
        self.run_dir = Path(run_dir)
        self.results = RunDir(self.run_dir).results
        self.version = 0
        """Counts the changes of `index` (a cache of anything derived from it keys on it)."""
        self.reloads = 0
        """Loads from the start (the first included)."""
        self._load()

    def _load(self) -> None:
        before = os.stat(self.results) if self.results.is_file() else None
        self.index = RunIndex.load(self.run_dir)  # raises RunDirError with a clear message
        self.reloads += 1
        self.version += 1
        # Lines appended while it loaded are read again by the next `refresh`, which skips
        # those it finds in the index already (same episode, same line).
        self._stat = before
        self._offset, self._lines = 0, 0
        if before is not None:
            with open(self.results, "rb") as f:
                data = f.read(before.st_size)
            self._offset = data.rfind(b"\n") + 1
            self._lines = data.count(b"\n", 0, self._offset)

    def refresh(self) -> bool:
        """Take in what the ledger gained since the last look; True if the index changed."""
        stat = os.stat(self.results)
        seen = self._stat
        if seen is not None and (stat.st_ino, stat.st_size, stat.st_mtime_ns) == (
            seen.st_ino,
            seen.st_size,
            seen.st_mtime_ns,
        ):
            return False
        if seen is None or stat.st_ino != seen.st_ino or stat.st_size < self._offset:
            self._load()
            return True
        with open(self.results, "rb") as f:
            f.seek(self._offset)
            data = f.read(stat.st_size - self._offset)
        whole = data[: data.rfind(b"\n") + 1]  # a line being written is read next time
        added = self._read(whole)
        if added is None:
            self._load()
            return True
        self._stat = stat
        self._offset += len(whole)
        self._lines += whole.count(b"\n")
        if not added:
            return False
        self._add(added)
        return True

    def _read(self, data: bytes) -> list[EpisodeRef] | None:
        """The new episodes of these whole lines; None if a line is anything else."""
        episodes = self.index.episodes
        added: list[EpisodeRef] = []
        new: set[str] = set()
        for n, raw in enumerate(data.split(b"\n")[:-1], self._lines + 1):
            if not raw.strip():
                continue
            try:
                record = read_line(raw, f"{self.results}:{n}", n)
            except (ReportError, ValueError):
                return None
            r = record.result
            rel = record.episode_dir or episode_rel(r.model, record.track, r.task, r.seed, r.run)
            ref = EpisodeRef(episode_id(rel), record.track, record)
            held = episodes.get(ref.id)
            if held is not None and held.record.line == n:
                continue  # read by the load this follows
            if held is not None or ref.id in new:
                return None
            new.add(ref.id)
            added.append(ref)
        return added

    def _add(self, added: list[EpisodeRef]) -> None:
        merged = heapq.merge(self.index.episodes.values(), sorted(added, key=_order), key=_order)
        self.index = RunIndex(self.index.run_dir, {ref.id: ref for ref in merged})
        self.version += 1


@dataclass(frozen=True)
class Row:
    """What the filters read of one episode."""

    id: str
    model: str
    track: str
    task: str
    outcome: str

    def passes(self, chosen: Mapping[str, str]) -> bool:
        return all(getattr(self, name) == value for name, value in chosen.items())


class Listing:
    """The run page's view of a `LiveIndex`: filter, page, neighbours (module docstring)."""

    def __init__(self, live: LiveIndex):
        self.live = live
        self._version = -1
        self._rows: list[Row] = []
        self._facets: dict[str, list[str]] = {}
        self._matched: dict[tuple[tuple[str, str], ...], list[Row]] = {}

    def _current(self) -> None:
        if self._version == self.live.version:
            return
        self._rows = [
            Row(ref.id, ref.result.model, ref.track, ref.result.task, outcome_of(ref))
            for ref in self.live.index.episodes.values()
        ]
        self._facets = {
            name: sorted({getattr(row, name) for row in self._rows}) for name in FILTERS
        }
        self._matched = {}
        self._version = self.live.version

    def matching(self, chosen: Mapping[str, str]) -> list[Row]:
        """The rows passing the filters `chosen` (by name; empty values are no filter)."""
        self._current()
        key = tuple(sorted((k, v) for k, v in chosen.items() if v and k in FILTERS))
        rows = self._matched.get(key)
        if rows is None:
            wanted = dict(key)
            rows = [row for row in self._rows if row.passes(wanted)] if key else self._rows
            if len(self._matched) >= 8:  # the last few filters: paging through them is free
                self._matched.pop(next(iter(self._matched)))
            self._matched[key] = rows
        return rows

    def page(self, chosen: Mapping[str, str], offset: int, limit: int) -> dict[str, Any]:
        rows = self.matching(chosen)
        episodes = self.live.index.episodes
        return {
            "total": len(self._rows),
            "matched": len(rows),
            "offset": offset,
            "limit": limit,
            "facets": self._facets,
            "episodes": [episodes[row.id] for row in rows[offset : offset + limit]],
        }

    def neighbours(self, chosen: Mapping[str, str], episode: str) -> dict[str, Any]:
        """The episodes before and after `episode` among those passing the filters (None at
        either end, or both when `episode` does not pass them)."""
        rows = self.matching(chosen)
        at = next((i for i, row in enumerate(rows) if row.id == episode), None)
        if at is None:
            return {"previous": None, "next": None, "position": None, "matched": len(rows)}
        return {
            "previous": rows[at - 1].id if at > 0 else None,
            "next": rows[at + 1].id if at + 1 < len(rows) else None,
            "position": at,
            "matched": len(rows),
        }


def filters_of(query: Mapping[str, str]) -> dict[str, str]:
    """The filters a request names (`FILTERS`; empty values dropped)."""
    return {name: query[name] for name in FILTERS if query.get(name)}


def paging_of(query: Mapping[str, str]) -> tuple[int, int]:
    """(offset, limit) of a request: whole numbers, the limit at most `MAX_PAGE`; ValueError
    naming the parameter otherwise."""
    out = []
    for name, default in (("offset", 0), ("limit", PAGE_SIZE)):
        text = query.get(name, "")
        try:
            value = int(text) if text else default
        except ValueError:
            raise ValueError(f"{name}: expected a whole number, got {text!r}") from None
        if value < 0 or (name == "limit" and not 1 <= value <= MAX_PAGE):
            raise ValueError(f"{name}: {value} is out of range")
        out.append(value)
    return out[0], out[1]
