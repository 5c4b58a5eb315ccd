"""Ctrl-C in the sweep: the first press stops it cleanly, the second at once.

First press: the running executor stops (the local one cancels its episodes at their next
await, the processes one ends its worker processes, the Ray one its engine actors). What was
recorded stays whole: a ledger line is one write of a whole line, a result.json is renamed into
place, and an episode cut short leaves only its partial events.jsonl, which the next run sets
aside before running it again. The command prints one line and exits with status 130. A second
press exits at once, with the same status and the same guarantees (nothing the sweep writes is
ever half a record).

The processes the sweep starts never see SIGINT (`vabench.children`); the sweep ends them.
"""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Callable, Iterator
from types import FrameType

EXIT_INTERRUPTED = 130
"""128 + SIGINT, what a shell reports for a command ended by Ctrl-C."""


class Interrupted(Exception):
    """Raised in the main thread at the first Ctrl-C where no executor took the press over."""


class CtrlC:
    """The sweep's SIGINT handler (main thread only)."""

    def __init__(self) -> None:
        self.pressed = 0
        self._on_first: Callable[[], object] | None = None
        self._previous: object = None

    def install(self) -> None:
        self._previous = signal.signal(signal.SIGINT, self._handle)

    def restore(self) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)  # type: ignore[arg-type]
            self._previous = None

    @contextlib.contextmanager
    def on_first(self, callback: Callable[[], object]) -> Iterator[None]:
        """Within the block, the first press calls `callback` (from the signal handler: it
        must only schedule the stop, e.g. `loop.call_soon_threadsafe(task.cancel)`) instead
        of raising `Interrupted`."""
        self._on_first = callback
        try:
            yield
        finally:
            self._on_first = None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.pressed += 1
        if self.pressed > 1:
            os.write(2, b"\nstopped at once; run the same command to resume\n")
            os._exit(EXIT_INTERRUPTED)
        if self._on_first is not None:
            self._on_first()
            return
        raise Interrupted()
