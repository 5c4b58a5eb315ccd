"""The sweep's ledger: RUN_DIR/results.jsonl, one line per finished planned episode.

Finished: scored, an `error` re-running cannot fix, or an `infrastructure_error` after its last
retry round; earlier infrastructure failures go to RUN_DIR/infrastructure.jsonl (rounds counted
across resumes) and the episode runs again. Appends are whole, fsynced and locked (`_locked`),
`open()` and `recover()` repair what a kill leaves, and with worker processes or Ray the driver
is the one writer (`Ledger(sink=...)`): every planned episode ends with exactly one line
(docs/RELIABILITY.md). In memory a line keeps its `OUTCOME` fields; the report and the viewer
read the file (`vabench.run_records`).
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import json
import os
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import TypeAdapter, ValidationError
from typing_extensions import TypedDict

from vabench.agent.records import RECORD_VERSION, EpisodeResult, read_result
from vabench.run_layout import DUPLICATES, INFRASTRUCTURE, RESULT, RESULTS, EpisodeDir, RunDir
from vabench.sweep.plan import EpisodeKey

Key = tuple[str, str, str, int, int]
Sink = Callable[[str, dict[str, Any]], None]
"""Where a ledger's appends go instead of its files: (`RESULTS` or `INFRASTRUCTURE`, record)."""


def key_of(record: dict[str, Any]) -> Key:
    return (
        record["model"],
        record["track"],
        record["task"],
        int(record["seed"]),
        int(record["run"]),
    )


def ledger_key(k: EpisodeKey) -> Key:
    """The ledger key of a planned `EpisodeKey` (the same tuple `key_of` reads from a line)."""
    return (k.model, k.track, k.task, int(k.seed), int(k.run))


class LedgerError(ValueError):
    pass


class Outcome(TypedDict, total=False):
    """What `Ledger.records` keeps of a line (what resuming, progress and the closing list of
    unscored episodes read); a line without the key's fields is not a record."""

    model: str
    track: str
    task: str
    seed: int
    run: int
    episode_dir: str
    status: str
    success: bool
    stop_reason: str
    error: str | None
    reopened: bool
    """On an infrastructure.jsonl line: a final infrastructure error moved back there to be run
    again (`reopen_infrastructure_errors`); its attempts are counted afresh from it."""


OUTCOME: tuple[str, ...] = tuple(Outcome.__annotations__)
_KEY = ("model", "track", "task", "seed", "run")
_OUTCOME = TypeAdapter(Outcome)


def outcome(record: dict[str, Any]) -> dict[str, Any]:
    """The `OUTCOME` fields of a whole record (one `add` builds or a worker sends)."""
    return {k: record[k] for k in OUTCOME if k in record}


def read_outcome(line: bytes) -> dict[str, Any]:
    """A ledger line's `OUTCOME` fields, validated from its JSON; `LedgerError`-worthy lines
    raise `ValueError` (pydantic's `ValidationError`, a missing key field)."""
    found = _OUTCOME.validate_json(line)
    missing = [k for k in _KEY if k not in found]
    if missing:
        raise ValueError(f"no {', '.join(missing)}")
    return dict(found)


@dataclass
class Ledger:
    """What has finished (loaded at start, appended as episodes end)."""

    run_dir: Path
    records: dict[Key, dict[str, Any]] = field(default_factory=dict)
    """Key -> the line's `OUTCOME` fields (the whole line stays in results.jsonl)."""
    infra_attempts: Counter = field(default_factory=Counter)
    sink: Sink | None = None
    """Set in a worker whose parent writes the logs (`executor: processes`)."""
    collapsed: list[str] = field(default_factory=list)
    """One line per duplicate record `open()` moved out of the ledger."""

    @classmethod
    def open(cls, run_dir: Path, sink: Sink | None = None) -> Ledger:
        run_dir.mkdir(parents=True, exist_ok=True)
        ledger = cls(run_dir, sink=sink)
        files = RunDir(run_dir)
        if files.results.exists():
            # A worker (sink set) never writes: it collapses in memory, its parent on disk.
            ledger.records, ledger.collapsed = _load_collapsing(
                files.results, files.duplicates, rewrite=sink is None
            )
        infra = files.infrastructure
        if infra.exists():
            for line in _read_whole_lines(infra):
                if line.strip():
                    attempt = read_outcome(line)
                    key = key_of(attempt)
                    if attempt.get("reopened"):  # its rounds start again after this line
                        ledger.infra_attempts[key] = 0
                    else:
                        ledger.infra_attempts[key] += 1
        return ledger

    def finished(self, key: Key) -> bool:
        return key in self.records

    def _append(self, name: str, record: dict[str, Any]) -> None:
        if self.sink is not None:
            self.sink(name, record)
            return
        data = (json.dumps(record) + "\n").encode("utf-8")
        with _locked(self.run_dir / name, os.O_WRONLY | os.O_APPEND | os.O_CREAT) as fd:
            end = os.lseek(fd, 0, os.SEEK_END)
            try:
                while data:  # one write() in practice; a short one is finished under the lock
                    data = data[os.write(fd, data) :]
                os.fsync(fd)
            except OSError as err:  # a full disk: the line is taken back, the sweep stops
                with contextlib.suppress(OSError):
                    os.ftruncate(fd, end)
                raise LedgerError(
                    f"cannot write {self.run_dir / name}: {err.strerror or err}. Every episode "
                    "recorded before this one is kept; make room and run the same command to "
                    "resume"
                ) from None

    def append_line(self, name: str, record: dict[str, Any]) -> None:
        """Append a line a worker built (`add`/`add_infrastructure_failure` through a sink);
        a second ledger record of an episode is refused (`LedgerError`)."""
        if name == RESULTS:
            key = key_of(record)
            if key in self.records:
                raise LedgerError(f"refusing a second record for {key}")
            self._append(RESULTS, record)
            self.records[key] = outcome(record)
        elif name == INFRASTRUCTURE:
            self._append(INFRASTRUCTURE, record)
            self.infra_attempts[key_of(record)] += 1
        else:
            raise ValueError(f"unknown log {name!r}")

    def add_duplicate(self, record: dict[str, Any]) -> None:
        """Keep a second record of an episode out of the ledger: in results.duplicates.jsonl,
        whose spend the report still bills (`executor: ray`, whose driver refuses it)."""
        self._append(DUPLICATES, record)

    def add(self, track: str, episode_dir: str, result: EpisodeResult) -> dict[str, Any]:
        record = _record(track, episode_dir, result)
        self.append_line(RESULTS, record)
        return record

    def add_infrastructure_failure(
        self, track: str, episode_dir: str, result: EpisodeResult
    ) -> None:
        self.append_line(INFRASTRUCTURE, _record(track, episode_dir, result))


def _record(track: str, episode_dir: str, result: EpisodeResult) -> dict[str, Any]:
    return {"v": RECORD_VERSION, "track": track, "episode_dir": episode_dir, **result.model_dump()}


def _load_collapsing(
    path: Path, aside: Path, rewrite: bool = True
) -> tuple[dict[Key, dict[str, Any]], list[str]]:
    """The ledger's records (`OUTCOME`s) by key; second records of a key are moved to `aside`
    (each line once, even if a crash repeats the move) and the ledger rewritten in place
    without them, all under the ledger's lock."""
    records: dict[Key, dict[str, Any]] = {}
    moved: dict[int, bytes] = {}
    notes: list[str] = []
    with _locked(path, os.O_RDWR) as fd:
        data = _whole_data(fd)
        for n, line in enumerate(io.BytesIO(data), 1):  # one line at a time, never a list
            if not line.strip():
                continue
            try:
                record = read_outcome(line)
                key = key_of(record)
            except (KeyError, TypeError, ValueError) as err:
                raise LedgerError(f"{path}:{n}: not a result record ({_why(err)})") from None
            if key in records:
                moved[n] = line.rstrip(b"\n")
                notes.append(
                    f"{path}:{n}: a second record for {'/'.join(map(str, key))} "
                    f"(status {record.get('status')}); kept the first, moved this one to "
                    f"{aside.name}"
                )
                continue
            records[key] = record
        if moved and rewrite:
            known = set(aside.read_bytes().splitlines()) if aside.exists() else set()
            with open(aside, "ab") as f:
                f.writelines(line + b"\n" for line in moved.values() if line not in known)
                f.flush()
                os.fsync(f.fileno())
            kept = (line for n, line in enumerate(io.BytesIO(data), 1) if n not in moved)
            _rewrite(fd, b"".join(line for line in kept if line.strip()))
    return records, notes


def _why(err: Exception) -> str:
    """One line of what is wrong with a line that is not a record."""
    if isinstance(err, ValidationError):
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        return f"{where + ': ' if where else ''}{first['msg']}"
    return str(err)


@contextlib.contextmanager
def _locked(path: Path, flags: int) -> Iterator[int]:
    """A descriptor of `path` holding an exclusive POSIX lock (NFS honours it across clients)
    until the block ends. Everything under the lock uses this descriptor: closing any other
    descriptor of the file would release the process's lock."""
    fd = os.open(path, flags, 0o644)
    try:
        try:
            fcntl.lockf(fd, fcntl.LOCK_EX)
        except OSError as err:
            raise LedgerError(f"{path}: cannot lock: {err.strerror or err}") from None
        yield fd
    finally:
        os.close(fd)  # releases the lock


def _read_whole_lines(path: Path) -> list[bytes]:
    """The lines of a JSONL log, after dropping a last line without its newline (a write cut
    short by a kill). Under the log's lock, so another process's append is never cut."""
    with _locked(path, os.O_RDWR) as fd:
        return _whole_data(fd).splitlines()


def _whole_data(fd: int) -> bytes:
    """A log's bytes up to its last newline, a line cut short cut off the file (the caller
    holds the lock). Bytes: the lines go to pydantic's JSON reader undecoded."""
    os.lseek(fd, 0, os.SEEK_SET)
    chunks = []
    while chunk := os.read(fd, 1 << 20):
        chunks.append(chunk)
    data = b"".join(chunks)
    if data and not data.endswith(b"\n"):
        data = data[: data.rfind(b"\n") + 1]
        os.ftruncate(fd, len(data))
    return data


def _rewrite(fd: int, data: bytes) -> None:
    """Replace a log's contents with `data`, on a descriptor whose lock the caller holds."""
    os.lseek(fd, 0, os.SEEK_SET)
    os.ftruncate(fd, 0)
    while data:
        data = data[os.write(fd, data) :]
    os.fsync(fd)


def set_aside(episode_dir: Path) -> None:
    """Move a finished-but-unusable attempt (an infrastructure error adopted on resume) out of
    the way, keeping it, so the episode can run again in the same directory."""
    files = EpisodeDir(episode_dir)
    aside = files.next_attempt()
    aside.mkdir()
    for path in files.attempt_files:
        if path.exists():
            path.rename(aside / path.name)


def reopen_infrastructure_errors(run_dir: Path, planned: set[Key] | None = None) -> list[Key]:
    """Move the ledger's `infrastructure_error` lines (of `planned` keys; None: all) back to
    the attempts log, marked `reopened`, and set their files aside, so the sweep runs them again
    with fresh retry rounds; returns their keys. Crash-safe in this order: the attempts log gets
    the line (once, however often a crash repeats this), the files go aside, the ledger drops it."""
    files = RunDir(run_dir)
    if not files.results.exists():
        return []
    with _locked(files.results, os.O_RDWR) as fd:
        data = _whole_data(fd)
        keep: list[bytes] = []
        reopen: list[tuple[Key, bytes, dict[str, Any]]] = []
        for line in io.BytesIO(data):
            if not line.strip():
                continue
            record = read_outcome(line)
            key = key_of(record)
            wanted = planned is None or key in planned
            if wanted and record.get("status") == "infrastructure_error":
                reopen.append((key, line, record))
            else:
                keep.append(line)
        if not reopen:
            return []
        marked = [
            (json.dumps({**json.loads(line), "reopened": True}) + "\n").encode("utf-8")
            for _, line, _ in reopen
        ]
        infra = files.infrastructure
        known = set(_read_whole_lines(infra)) if infra.exists() else set()
        with _locked(infra, os.O_WRONLY | os.O_APPEND | os.O_CREAT) as log_fd:
            for line in marked:
                if line.rstrip(b"\n") not in known:
                    os.write(log_fd, line)
            os.fsync(log_fd)
        for _, _, record in reopen:
            episode = run_dir / record["episode_dir"]
            if (episode / RESULT).exists():
                set_aside(episode)
        _rewrite(fd, b"".join(keep))
    return [key for key, _, _ in reopen]


def recover(run_dir: Path, episode_dir: str) -> EpisodeResult | None:
    """The result.json of an episode that finished but never reached the ledger, if any
    (asked of every unfinished episode on resume: a missing one costs one `stat`)."""
    if not os.path.exists(os.path.join(run_dir, episode_dir, RESULT)):
        return None
    return read_result(run_dir / episode_dir)
