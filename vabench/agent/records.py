"""Episode records: the append-only event log, the frames the model saw, and the result.

Layout (docs/DESIGN.md, "Run directory"; the names are `vabench.run_layout`'s), under the
episode's directory:

    events.jsonl          one JSON object per line, appended and flushed as it happens
    frames/step_NNN.jpg   the clean image the model saw with the observation of step NNN
                          ("Step NNN of B"; step_001 right after reset), the numbering the
                          model uses in camera.history; passive: step_NNN_K_<view>.jpg,
                          K = 0..4 in the bundle's fixed order
    result.json           written once, atomically, when the episode ends

Every line and the result carry `"v": RECORD_VERSION`. Events are versioned dicts rather
than one pydantic model per type: the engine adds fields as it learns more, and readers
(the sweep's resume logic, the report) key on `type` and ignore what they do not know.

Status vocabulary (`EpisodeResult.status`): "success" and "failure" are scored; an
"infrastructure_error" (provider or renderer outlasted its retries) is re-run by the sweep and
never scored; "error" is a harness or configuration problem (a seed that fails its reset, a
request the provider rejects as malformed) that re-running will not fix, also never scored.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import shutil
import threading
import time
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from vabench.run_layout import EpisodeDir, frame_path

RECORD_VERSION = 1

Status = Literal["success", "failure", "infrastructure_error", "error"]
SCORED: tuple[Status, ...] = ("success", "failure")
SummaryStatus = Literal["none", "learned", "failed"]


class TokenTotals(BaseModel):
    model_config = ConfigDict(extra="forbid")
    input: int = 0
    cached_input: int = 0
    cache_write: int = 0
    output: int = 0
    reasoning: int = 0


class EpisodeResult(BaseModel):
    """result.json: how one episode ended."""

    model_config = ConfigDict(extra="forbid")
    v: int = RECORD_VERSION
    task: str
    seed: int
    model: str
    protocol: Literal["active", "passive"]
    run: int
    status: Status
    success: bool
    stop_reason: str
    """success | model_stop | budget_exhausted | invalid_output | refused | truncated |
    context_exceeded | round_trip_limit | infrastructure_error | request_rejected |
    reset_failed | harness_error. `refused`, `truncated` (the repairs of a decision ran out on
    a refusal / a reply cut at the output limit) and `context_exceeded` (the model's context
    could not hold the episode after one compaction) are the model's failures: scored."""
    error: str | None = None
    steps_used: int = 0
    step_budget: int
    robot_actions: int = 0
    camera_actions: int = 0
    invalid_outputs: int = 0
    """Replies rejected by the protocol (each got a repair turn, or ended the episode); the
    three counts below are kinds of them."""
    refusals: int = 0
    """Replies that were a refusal (or a provider's content filter)."""
    truncations: int = 0
    """Replies cut at the output limit without a whole decision."""
    empty_replies: int = 0
    """Replies with no answer text (nothing, or reasoning only)."""
    invalid_actions: int = 0
    """Executed robot actions the simulator refused (invalid for the scene) or could not plan."""
    tool_calls: int = 0
    model_calls: int = 0
    compactions: int = 0
    checkpoints_reached: list[str] = Field(default_factory=list)
    progress: int = 0
    n_checkpoints: int
    tokens: TokenTotals = Field(default_factory=TokenTotals)
    cost_usd: float = 0.0
    wall_s: float = 0.0
    started_at: float = 0.0
    summary_mode: str = "none"
    """Whose demonstration summary the track reads: own | none | shared:<model>."""
    summary_from: str | None = None
    """The model whose summary every observation carried; None when none was shown."""
    summary_status: SummaryStatus = "none"
    """learned (shown), failed (that model's learning ended without a summary: none shown),
    none (the track reads no summary)."""

    @property
    def scored(self) -> bool:
        return self.status in SCORED


class _Writes:
    """The frame files of one recorder still being written, and the first error."""

    def __init__(self) -> None:
        self._done = threading.Condition()
        self.pending = 0
        self.error: OSError | None = None

    def add(self) -> None:
        with self._done:
            self.pending += 1

    def finished(self, error: OSError | None) -> None:
        with self._done:
            self.pending -= 1
            self.error = self.error or error
            self._done.notify_all()

    def wait(self) -> None:
        """Until every frame handed over is on disk; the first write error is raised."""
        with self._done:
            self._done.wait_for(lambda: self.pending == 0)
            if self.error is not None:
                error, self.error = self.error, None
                raise error


class _FrameWriter:
    """One thread writing every episode's frames: a frame is ~150 KB of JPEG at 1280x960, a
    sweep writes ~140,000 of them, and written on the event loop they were a fifth of its busy
    time (py-spy of the suite on a GPU). A write releases the GIL; the loop
    only hands the bytes over."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[tuple[Path, bytes, _Writes]] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._start = threading.Lock()

    def submit(self, path: Path, data: bytes, writes: _Writes) -> None:
        writes.add()
        with self._start:
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="frame-writer", daemon=True)
                self._thread.start()
        self._queue.put((path, data, writes))

    def _run(self) -> None:
        while True:
            path, data, writes = self._queue.get()
            error: OSError | None = None
            try:
                path.write_bytes(data)
            except OSError as err:
                error = err
            writes.finished(error)


_FRAMES = _FrameWriter()


class EpisodeRecorder:
    """Writes one episode's records; with `directory=None` it keeps events in memory only.
    Frames are written by a thread of their own (`_FrameWriter`); `finish` and `close` wait for
    them, so a result.json never exists without its frames, and a write error surfaces at the
    episode's next frame or at its end."""

    def __init__(self, directory: Path | str | None, frames: str = "all"):
        """`frames`: which episodes keep their images (`all`, `failed`, `none`)."""
        self.directory = Path(directory) if directory is not None else None
        self.keep_frames = frames
        self.events: list[dict[str, Any]] = []
        self._file = None
        self._seq = 0
        self._writes = _Writes()
        if self.directory is not None:
            files = EpisodeDir(self.directory)
            if files.result.exists():
                raise FileExistsError(
                    f"{self.directory} already holds a finished episode; refusing to overwrite"
                )
            self._set_aside_partial(files)
            files.frames.mkdir(parents=True, exist_ok=True)
            self._file = open(files.events, "a", encoding="utf-8")  # noqa: SIM115

    @staticmethod
    def _set_aside_partial(files: EpisodeDir) -> None:
        """An interrupted earlier attempt (events but no result) is kept, renamed, never
        appended to: a re-run starts a clean log."""
        if not files.events.exists():
            return
        aside = files.next_partial()
        aside.mkdir()
        files.events.rename(aside / files.events.name)
        if files.frames.exists():
            files.frames.rename(aside / files.frames.name)

    def event(self, type_: str, **fields: Any) -> dict[str, Any]:
        record = {
            "v": RECORD_VERSION,
            "seq": self._seq,
            "t": round(time.time(), 4),
            "type": type_,
            **fields,
        }
        self._seq += 1
        self.events.append(record)
        if self._file is not None:
            self._file.write(json.dumps(record, default=_json_default) + "\n")
            self._file.flush()
        return record

    def frame(
        self, step: int, jpeg: bytes, view: str | None = None, index: int | None = None
    ) -> str:
        """Store one model image; returns its path relative to the episode directory."""
        rel = frame_path(step, view, index)
        if self.directory is not None and self.keep_frames != "none":
            if self._writes.error is not None:
                self._writes.wait()  # raises the earlier write's error in this episode
            _FRAMES.submit(self.directory / rel, jpeg, self._writes)
        return rel

    def finish(self, result: EpisodeResult) -> EpisodeResult:
        self.event(
            "end",
            status=result.status,
            stop_reason=result.stop_reason,
            success=result.success,
            error=result.error,
        )
        if self.directory is not None:
            self._writes.wait()
            path = EpisodeDir(self.directory).result
            tmp = path.with_name(f"{path.name}.tmp")
            tmp.write_text(result.model_dump_json(indent=1), encoding="utf-8")
            os.replace(tmp, path)
            if self.keep_frames == "failed" and result.success:  # after the result: kept whole
                shutil.rmtree(EpisodeDir(self.directory).frames, ignore_errors=True)
        self.close()
        return result

    def close(self) -> None:
        with contextlib.suppress(OSError):  # the episode has ended (or failed): its log says so
            self._writes.wait()
        if self._file is not None:
            self._file.close()
            self._file = None


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, BaseModel):
        return value.model_dump(exclude_none=True)
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def read_events(directory: Path | str) -> list[dict[str, Any]]:
    """The events of one episode (a truncated last line, from a crash mid-write, is dropped)."""
    events = []
    with open(EpisodeDir(Path(directory)).events, encoding="utf-8") as f:
        for line in f:
            try:
                events.append(json.loads(line))
            except json.JSONDecodeError:
                break
    return events


def read_result(directory: Path | str) -> EpisodeResult | None:
    path = EpisodeDir(Path(directory)).result
    if not path.exists():
        return None
    return EpisodeResult.model_validate_json(path.read_text(encoding="utf-8"))
