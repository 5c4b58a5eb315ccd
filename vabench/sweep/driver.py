"""The one driver of a sweep over engines (in-process, worker processes or Ray actors, each
running its chunks with a `chunk_engine.ChunkEngine`): it serves one limit board to all of them,
hands out chunks as engines have room (`placement.next_placement`), is the only writer of the
ledger and merges the engines' statuses for the display. A dead engine costs only its unrecorded
episodes: they go back to the front of the queue and another engine takes its place, at most
`Engines.max_restarts` times. A stopped endpoint or spend cap ends the handing out
(`SweepStopped`); a disk below its reserve and Ctrl-C end every engine at the next tick, every
whole ledger line they sent kept.

Engines report events into one queue, in the order each sends them: (STARTED, info),
(LINE, log, record), (DONE, chunk, summary), (FAILED, chunk, error), (STATUS, status),
(LOST, why, replace) and (CLOSED, figures).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import queue
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from typing_extensions import TypedDict, Unpack

from vabench.config import SweepConfig
from vabench.config.choices import Choices
from vabench.llm_pool.limit_board import shared_endpoints
from vabench.llm_pool.spend import SpendCaps
from vabench.run_layout import DUPLICATES, RESULTS
from vabench.sweep import rundir
from vabench.sweep.cells import PROGRESS_EVERY_S, Cell, pending_cells
from vabench.sweep.chunk_engine import (
    CLOSED,
    DONE,
    FAILED,
    LINE,
    LOST,
    STARTED,
    STATUS,
    BoardLink,
)
from vabench.sweep.display import Status, Tally, with_reports
from vabench.sweep.interrupt import CtrlC, Interrupted
from vabench.sweep.placement import Chunk, Engine, EngineHandle, next_placement
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import Key, Ledger, LedgerError, key_of, ledger_key
from vabench.sweep.runner import SweepStopped, spend_caps

TICK_S = 1.0
"""Seconds between display updates (and the longest the driver waits for an event)."""
MAX_ENGINE_RESTARTS = 16
"""Engines started in place of dead ones, in one invocation (worker processes, Ray actors)."""
ENGINE_START_TIMEOUT_S = 900.0
"""How long the driver waits for an engine while none runs (a node may download the project,
compile, build demonstrations) before it gives up, listing what did not run."""
CLOSE_TIMEOUT_S = 60.0
"""How long the engines have to close at the end before they are ended."""

Emit = Callable[..., None]
"""An engine's way to report an event (its items after the engine)."""


class Engines:
    """An executor's kind of engine and its plan (each executor's subclass), for the sweep of
    `config` into `run_dir` on `choices`."""

    label: str
    """Its name in the log ("local", "processes", "ray")."""
    unit = "engines"
    """What its engines are called in the display ("worker processes", "engines")."""
    log: logging.Logger
    max_chunks = 1
    """Chunks at once in one engine."""
    engines_wanted: int
    chunks: list[Chunk]
    """The plan, costliest first."""
    max_restarts = MAX_ENGINE_RESTARTS
    """Engines started in place of dead ones."""
    shares_board = True
    """Its engines share one limit board (`serve_board`); else its one engine's pool keeps
    the limits and spend caps itself."""

    def __init__(self, config: SweepConfig, choices: Choices, run_dir: Path):
        self.config = config
        self.choices = choices
        self.run_dir = run_dir

    def fits(self) -> bool:
        """Whether its engines can start at all (else it says why)."""
        return True

    def serve_board(
        self, stack: contextlib.ExitStack, limits: dict[str, dict[str, Any]], caps: SpendCaps | None
    ) -> BoardLink:
        """The sweep's one limit board, served to its engines until `stack` closes."""
        raise NotImplementedError

    def prepare(self, stack: contextlib.ExitStack) -> None:
        """What its engines need before they start (closed with `stack`, after them)."""

    def new_engine(self, index: int, slot: int, emit: Emit, board: BoardLink | None) -> Engine:
        """Engine `index`, filling plan slot `slot`."""
        raise NotImplementedError


Cells = dict[Cell, list[EpisodeKey]]
"""The planned episodes without a record, by cell."""


class Hooks(TypedDict, total=False):
    """What the command hands each executor's `run_*` for the driver."""

    on_status: Callable[[Status], None] | None
    """Called about once a second."""
    on_engines: Callable[[list[dict[str, Any]]], None] | None
    """Called once at the end with `Driver.engine_report()` (each engine's time and GPU busy
    share)."""
    ctrl_c: CtrlC | None
    """The command's handler, else Ctrl-C is not the driver's."""


def run_engines(
    open_engines: Callable[[Cells], contextlib.AbstractContextManager[Engines]],
    log: logging.Logger,
    label: str,
    keys: Sequence[EpisodeKey],
    run_dir: Path,
    **hooks: Unpack[Hooks],
) -> dict[Key, dict[str, Any]]:
    """Run the pending episodes of `keys` on the engines `open_engines(cells)` opens, under one
    `Driver`; return the ledger's records afterwards (each executor's `run_*`)."""
    ledger = Ledger.open(run_dir)  # second records of an episode moved aside, and said
    for line in ledger.collapsed:
        log.warning("ledger: %s", line)
    cells = pending_cells(keys, ledger.records)
    if not cells:
        log.info("%s: every planned episode is already in %s; nothing to run", label, RESULTS)
        return ledger.records
    with open_engines(cells) as kind:
        driver = Driver(kind, keys, ledger, hooks.get("on_status"), hooks.get("ctrl_c"))
        try:
            return driver.run()
        finally:
            if (on_engines := hooks.get("on_engines")) is not None:
                try:
                    on_engines(driver.engine_report())
                except Exception:  # the caller's report must not hide the sweep's own error
                    log.exception("%s: on_engines failed", label)


class _DiskShort(Exception):
    """The run directory's disk is below the reserve (`rundir.disk_short`)."""


class Driver:
    """The driver's loop (see the module docstring) over the engines of `kind`."""

    def __init__(
        self,
        kind: Engines,
        keys: Sequence[EpisodeKey],
        ledger: Ledger,
        on_status: Callable[[Status], None] | None = None,
        ctrl_c: CtrlC | None = None,
    ):
        """`ledger`: the run directory's (`run_engines` opened it), of which it is the only
        writer."""
        self.kind = kind
        self.log = kind.log
        self.config = kind.config
        self.run_dir = kind.run_dir
        self.on_status = on_status
        self.ctrl_c = ctrl_c
        self.pressed = False
        """Ctrl-C was pressed (`ctrl_c`'s first press): the loop ends at its next tick."""
        self.ledger = ledger
        self.tally = Tally(self.run_dir, keys)
        self.queue: collections.deque[Chunk] = collections.deque(kind.chunks)
        self.total = len(self.queue)
        self.done = 0
        self.failures: list[Chunk] = []
        self.stopped: list[str] = []
        self.engines: list[EngineHandle] = []
        self.restarts = 0
        self.events: queue.Queue[tuple[Any, ...]] = queue.Queue()
        self.board: BoardLink | None = None
        self._changed = False
        """A chunk ended or an engine came or went since the last progress line."""
        self.started_at = time.monotonic()

    def _say(self, level: int, message: str, *args: Any) -> None:
        self.log.log(level, f"{self.kind.label}: {message}", *args)

    # -- the run -------------------------------------------------------------------------------
    def run(self) -> dict[Key, dict[str, Any]]:
        """Run the chunks; return the ledger's records. Raises `SweepStopped` when an endpoint,
        a spend cap or the GPUs stopped it."""
        if not self.kind.fits():
            self.failures.extend(self.queue)
            self.queue.clear()
        else:
            with contextlib.ExitStack() as stack:
                finished = False
                try:
                    self.board = self._serve_board(stack)
                    self.kind.prepare(stack)
                    for slot in range(self.kind.engines_wanted):
                        self._start_engine(slot)
                    with self._ctrl_c():
                        self._loop()
                    finished = True
                except _DiskShort:
                    pass
                finally:
                    self._end(gracefully=finished)
        if self.failures:
            self._say(
                logging.ERROR,
                "%d chunks failed (%d episodes not run): %s",
                len(self.failures),
                sum(len(c.keys) for c in self.failures),
                ", ".join(c.name for c in self.failures),
            )
        if self.stopped:
            raise SweepStopped(self.stopped[0])
        return self.ledger.records

    def _ctrl_c(self) -> contextlib.AbstractContextManager[None]:
        """Within the block, a first Ctrl-C is noted (`pressed`) for the loop's next tick."""
        if self.ctrl_c is None:
            return contextlib.nullcontext()

        def press() -> None:  # in the signal handler: a flag, no lock (the queue's) taken
            self.pressed = True

        return self.ctrl_c.on_first(press)

    def _serve_board(self, stack: contextlib.ExitStack) -> BoardLink | None:
        """One limit board for every engine: the limits of each endpoint the embedded server
        does not serve (each engine's embedded server keeps its own), and the spend caps over
        what the run directory already spent. None when there is nothing to keep."""
        if not self.kind.shares_board:
            return None
        limits = shared_endpoints(self.config.models, self.config.embedded_models)
        caps = spend_caps(self.config, self.run_dir)
        if not limits and caps is None:
            return None
        board = self.kind.serve_board(stack, limits, caps)
        kept = [f"the limits of {', '.join(limits)}"] if limits else []
        kept += ["the spend caps"] if caps is not None else []
        self._say(logging.INFO, "one limit board for every engine keeps %s", " and ".join(kept))
        return board

    def _loop(self) -> None:
        last_log = idle_since = time.monotonic()
        while self.queue or any(e.chunks for e in self.engines):
            if self.pressed:
                raise Interrupted()
            self._check_disk()
            self._hand_out()
            try:
                event = self.events.get(timeout=TICK_S)
                while True:
                    self._handle(*event)
                    event = self.events.get_nowait()
            except queue.Empty:
                pass
            if any(e.ready for e in self.engines):
                idle_since = time.monotonic()
            elif not self._can_start() or time.monotonic() - idle_since > ENGINE_START_TIMEOUT_S:
                self._give_up()
            self.tally.refresh()
            if self.on_status is not None:
                self.on_status(self.status())
            if self._changed or time.monotonic() - last_log >= PROGRESS_EVERY_S:
                last_log, self._changed = time.monotonic(), False
                self._say(
                    logging.INFO,
                    "chunks %d/%d done (%d failed), %d running on %d engines | episodes "
                    "recorded %d/%d",
                    self.done,
                    self.total,
                    len(self.failures),
                    sum(len(e.chunks) for e in self.engines),
                    sum(e.ready for e in self.engines),
                    self.tally.status().total().done,
                    len(self.tally.planned),
                )

        self._check_disk()  # the last records found it short: the sweep ended, and says so

    def _check_disk(self) -> None:
        """Before a write fails: the engines are ended at once (`_DiskShort`), their
        unrecorded episodes run again on resume."""
        if (why := rundir.disk_short(self.run_dir)) is not None:
            self.stopped.append(why)
            raise _DiskShort

    def _handle(self, engine: EngineHandle, event: str, *payload: Any) -> None:
        if event == CLOSED:
            engine.final = payload[0] or {}
        if engine.dead:  # what a lost engine said after it was taken for dead: run again
            return
        if event == STARTED:
            engine.starting = False
            engine.info = payload[0]
            engine.clock.started_at = time.monotonic()
            engine.status = {"limit": engine.info.get("limit", 1)}
            self._changed = True
            self._say(logging.INFO, "engine %d started: %s", engine.index, engine.info)
        elif event == LINE:
            if self._append(*payload):
                engine.clock.episodes += 1
        elif event == DONE:
            self._done(engine, *payload)
        elif event == FAILED:
            name, error = payload
            self.failures.append(self._chunk_over(engine, name))
            self._say(logging.ERROR, "chunk %s failed on %s:\n%s", name, _host(engine), error)
        elif event == STATUS:
            engine.status = payload[0]
        elif event == LOST:
            self._lost(engine, *payload)

    # -- engines -------------------------------------------------------------------------------
    def _start_engine(self, slot: int) -> None:
        handle = EngineHandle(len(self.engines), slot=slot)

        def emit(*event: Any) -> None:
            self.events.put((handle, *event))

        handle.engine = self.kind.new_engine(handle.index, slot, emit, self.board)
        self.engines.append(handle)
        handle.engine.start(sorted({k.task for c in self.queue for k in c.keys}))

    def _can_start(self) -> bool:
        return any(e.starting and not e.dead for e in self.engines)

    def _lost(
        self, engine: EngineHandle, why: str, replace: bool = True, stopped: str | None = None
    ) -> None:
        """`engine` is gone (or its GPU failed, `stopped` saying so): its chunks' episodes
        without a record go back to the queue's front and another engine takes its place."""
        engine.dead = True
        engine.clock.end(time.monotonic())
        self._changed = True
        requeued = 0
        for chunk in reversed(list(engine.chunks.values())):
            left = [k for k in chunk.keys if ledger_key(k) not in self.ledger.records]
            if left:
                name = chunk.name if chunk.name.endswith(" (again)") else f"{chunk.name} (again)"
                self.queue.appendleft(Chunk(name, left, chunk.cost, chunk.critical))
                self.total += 1
                requeued += len(left)
            self.done += 1  # this try of the chunk has ended
        engine.chunks.clear()
        _engine(engine).kill()
        restart = replace and self.restarts < self.kind.max_restarts
        self._say(
            logging.WARNING,
            "engine %d (%s) is gone: %s; %d unfinished episodes go back to the queue%s",
            engine.index,
            engine.info.get("host", "not started"),
            why,
            requeued,
            "; starting another engine" if restart else "; no engine is started in its place",
        )
        if restart:
            self.restarts += 1
            self._start_engine(engine.slot)
        elif stopped is not None and not self.stopped:
            self.stopped.append(stopped)
            self.queue.clear()

    def _give_up(self) -> None:
        """No engine runs and none will: what is left is not run this time."""
        self._say(
            logging.ERROR,
            "no engine is running and %s; %d chunks not run",
            f"none has started in {ENGINE_START_TIMEOUT_S:.0f} s"
            if self._can_start()
            else "none is starting",
            len(self.queue),
        )
        self.failures.extend(self.queue)
        self.queue.clear()
        for e in self.engines:
            if not e.dead and e.starting:
                e.dead = True
                e.clock.end(time.monotonic())
                _engine(e).kill()

    # -- chunks --------------------------------------------------------------------------------
    def _hand_out(self) -> None:
        """Give the queue's chunks to engines with room (`placement.next_placement`)."""
        while self.queue and not self.stopped:
            placed = next_placement(
                self.engines, self.queue, self.ledger.records, self.kind.max_chunks
            )
            if placed is None:
                return
            at, best = placed
            chunk = self.queue[at]
            del self.queue[at]
            best.given.append(chunk)
            best.chunks[chunk.name] = chunk
            best.clock.work_began(time.monotonic())
            _engine(best).run_chunk(chunk)
            self._say(
                logging.INFO,
                "chunk %s (%d episodes) to %s",
                chunk.name,
                len(chunk.keys),
                _host(best),
            )
            if chunk.critical and not best.lead:  # its GPU's normal engine busy or not started
                self._say(
                    logging.WARNING,
                    "critical chunk %s runs below normal MPS priority on %s: the engines at "
                    "normal priority on its GPU go ahead of it",
                    chunk.name,
                    _host(best),
                )

    def _done(self, engine: EngineHandle, name: str, summary: dict[str, Any]) -> None:
        self._say(logging.INFO, "chunk %s done on %s: %s", name, _host(engine), summary)
        if summary.get("device_failed"):  # a new process has a new context
            stopped = summary["stopped"]
            self._lost(engine, f"its GPU failed ({stopped})", stopped=stopped)
            return
        self._chunk_over(engine, name)
        if summary.get("stopped") and not self.stopped:
            self.stopped.append(summary["stopped"])
            self.queue.clear()

    def _chunk_over(self, engine: EngineHandle, name: str) -> Chunk:
        chunk = engine.chunks.pop(name)
        if not engine.chunks:
            engine.clock.work_ended(time.monotonic())
        self.done += 1
        self._changed = True
        return chunk

    def _append(self, name: str, record: dict[str, Any]) -> bool:
        """Append a ledger line; False when it was an episode's second record."""
        if name == RESULTS and key_of(record) in self.ledger.records:
            # an episode reported twice (an engine taken for dead)
            self._say(
                logging.WARNING, "a second record for %s; kept in %s", key_of(record), DUPLICATES
            )
            self.ledger.add_duplicate(record)
            return False
        try:
            self.ledger.append_line(name, record)
        except LedgerError:
            raise  # the disk is full: the sweep stops, every record before it kept
        except (KeyError, ValueError) as err:  # a line that is no record
            self._say(logging.ERROR, "a %s line was not written: %s", name, err)
            return False
        return True

    # -- status --------------------------------------------------------------------------------
    def status(self) -> Status:
        """The ledger's counts with what the engines report (running, in flight, spend)."""
        reports = [e.status for e in self.engines if "calls" in e.status]
        live = [e.status for e in self.engines if e.ready and "calls" in e.status]
        return with_reports(self.tally.status(), reports, live, self.kind.unit)

    # -- the end -------------------------------------------------------------------------------
    def _end(self, gracefully: bool) -> None:
        """Close the engines (or, interrupted, end them at once), keeping every whole line
        they sent, and log each one's time."""
        live = [e for e in self.engines if not e.dead]
        now = time.monotonic()
        for e in self.engines:
            e.clock.end(now)
        try:
            if gracefully:
                self._close([e for e in live if e.ready], now + CLOSE_TIMEOUT_S)
        finally:  # those still closing at the deadline (or when it was cut short) end at once
            for e in live:
                _engine(e).kill()
        with contextlib.suppress(queue.Empty):
            while True:
                engine, event, *payload = self.events.get_nowait()
                if event == LINE and not engine.dead:
                    self._append(*payload)
        if self.engines:
            try:
                self._log_engine_time()
            except Exception:  # a report, never a reason to lose the sweep's own error
                self.log.exception("%s: the engines' time could not be reported", self.kind.label)

    def _close(self, ready: list[EngineHandle], deadline: float) -> None:
        """Ask the `ready` engines to close; wait for them until `deadline`, keeping the lines
        they send meanwhile."""
        closing = {id(e) for e in ready}
        for e in ready:
            _engine(e).close()
        while closing and time.monotonic() < deadline:
            with contextlib.suppress(queue.Empty):
                engine, event, *payload = self.events.get(timeout=TICK_S)
                if event == CLOSED:
                    engine.final = payload[0] or {}
                    closing.discard(id(engine))
                elif event == LINE and not engine.dead:
                    self._append(*payload)

    def engine_report(self) -> list[dict[str, Any]]:
        """Per engine: where it ran (its host and GPU ids), its seconds of start-up, working (a
        chunk or more) and waiting for work, the episodes it recorded, the chunks it was given
        (those of the critical path apart), whether it was its GPU's lead (the normal MPS
        priority of a ranked sweep), whether it died, and its GPU's busy share over its life and
        most memory (None where not sampled)."""
        now = time.monotonic()
        return [
            {
                "engine": e.index,
                "host": e.info.get("host"),
                "gpus": e.info.get("gpus"),
                **e.clock.figures(now),
                "episodes": e.clock.episodes,
                "chunks": len(e.given),
                "critical_chunks": [c.name for c in e.given if c.critical],
                "lead": e.lead,
                "died": e.dead,
                "gpu_busy": (e.final or e.status).get("gpu_busy"),
                "gpu_memory_mib": (e.final or e.status).get("gpu_memory_mib"),
            }
            for e in self.engines
        ]

    def _log_engine_time(self) -> None:
        report = self.engine_report()
        for r in report:
            gpu = f", GPU busy {r['gpu_busy']:.0%}" if r["gpu_busy"] is not None else ""
            self._say(
                logging.INFO,
                "engine %d (%s): start-up %.1f s, working %.1f s, waiting for work %.1f s, "
                "%d episodes%s%s",
                r["engine"],
                r["host"] or "not started",
                r["start_up_s"],
                r["working_s"],
                r["waiting_s"],
                r["episodes"],
                gpu,
                ", died" if r["died"] else "",
            )
        total = sum(r["life_s"] for r in report)
        if total > 0:
            self._say(
                logging.INFO,
                "engine time %.0f s over %d engines (%.0f s of sweep): start-up %.0f %%, "
                "working %.0f %%, waiting for work %.0f %%",
                total,
                len(report),
                time.monotonic() - self.started_at,
                100 * sum(r["start_up_s"] for r in report) / total,
                100 * sum(r["working_s"] for r in report) / total,
                100 * sum(r["waiting_s"] for r in report) / total,
            )


def _engine(handle: EngineHandle) -> Engine:
    assert handle.engine is not None, "started by `Driver._start_engine`"
    return handle.engine


def _host(engine: EngineHandle) -> str:
    return f"engine {engine.index} ({engine.info.get('host', '?')})"
